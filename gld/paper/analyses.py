"""What each analysis of a paper suite computes (`gld.paper.tasks` schedules them).

Each function takes the suite's runner (its data, its trained runs, its results
directory) and returns the analysis's result: the classical references, the pose probe
and triangulation with its pose, the flow-error curves, the qualitative predictions, the
generated filters, the learned flow network against DIS, the flow networks after depth
training, and where the main run beats the classical pipeline pair by pair. Arrays a
later task or the report reads go to <results>/<task>.npz.
"""

from __future__ import annotations

import dataclasses
import io
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from gld import contract
from gld import files as files_lib
from gld import flow as flow_lib
from gld.analysis import encoder_pose, regimes_run
from gld.analysis import filter_inspection as inspect_lib
from gld.analysis import flow_error as flow_error_lib
from gld.evaluation import evaluate as evaluation
from gld.evaluation import flow_network, trained_run
from gld.models import flow_net as flow_net_lib
from gld.models.baselines import classical as classical_lib
from gld.models.flow_net import FlowNet
from gld.paper import run_configs
from gld.paper import suite as paper_suite
from gld.paper.result_files import read_result
from gld.paper.scales import Scale
from gld.runs import metrics_log


class Runner(Protocol):
    """What an analysis reads of the suite's training runs
    (`gld.paper.training_runs.TrainingRuns`; the suite's runner is one)."""

    scale: Scale
    results_dir: Path
    print: Callable[[str], None]

    def data(self, dataset: str) -> Any: ...

    def compared_run(self, name: str) -> str: ...

    def flow_net_dir(self) -> Path: ...

    def trained(self, name: str) -> Any: ...

    def fit_flow_net(self, *, evaluate: bool) -> Any: ...


# Classical methods of the main dataset, and of the varying-intrinsics one.
CLASSICAL = ("dataset_mean", "oracle_pair_median", "triangulation_gt_pose", "sfm_flow")

MAIN_RUN = "global_local_1px"
# The pose probe reads the encoders of the main run, whose motion terms (the epipolar
# term, the pose teacher) train g to be the camera motion, and of the run without them
# (g learned from depth alone: the paper's setting).
PROBED_RUNS = (MAIN_RUN, "global_local_no_epipolar")
# Triangulation with a predicted pose uses the main run's encoder, fine-tuned on the pose.
PREDICTED_POSE = (MAIN_RUN, "pretrained_full")
FILTER_PAIRS = 16
# Test pairs whose DIS flow is timed for the flow network's speed comparison.
DIS_TIMED_PAIRS = 20
# The qualitative grid's columns (besides image and truth), in order: each model at the
# rate of its learning-rate check that its comparisons use.
QUALITATIVE_RUNS = ("small_encdec_1px", "dispnet_1px", "global_local_1px")
# The per-pair comparison sets the main run (at its compared rate) against the classical
# pipeline on the same flow, by property tercile.
REGIMES_REFERENCE = "sfm_flow"
REGIMES_BINS = 3


def write_npz(path: Path, **arrays: np.ndarray) -> None:
    """An analysis's arrays, compressed and written atomically."""

    path.parent.mkdir(parents=True, exist_ok=True)
    buffer = io.BytesIO()
    np.savez_compressed(buffer, **arrays)
    files_lib.write_atomically(path, buffer.getvalue())


def scores(per_example: dict[str, np.ndarray]) -> tuple[dict[str, dict], np.ndarray]:
    """The evaluation's summary and each real example's Abs-Inv."""

    summary, _ = evaluation.summarise_examples(per_example)
    return summary, np.asarray(per_example["abs_inv"])[np.asarray(per_example["example_mask"])]


def flow_net(runner: Runner) -> dict[str, Any]:
    """Trains the flow network on the exact flow (or resumes it), then scores it and
    the stored DIS flow on the test pairs: end-point errors and time per pair."""

    data = runner.data(runner.scale.dataset)
    run_dir = runner.flow_net_dir()
    runner.print(f"flow_net: {runner.scale.flow_net_steps} steps of the flow network in {run_dir}")
    model, variables, step, summary = runner.fit_flow_net(evaluate=True)
    latency = flow_network.forward_latency(model, variables, data.height, data.width)
    count = min(DIS_TIMED_PAIRS, len(data.test))
    batch = next(
        evaluation.split_batches(
            data.test, batch_size=count, max_examples=count, all_processes=False
        )
    )
    times = []
    for image1, image2 in zip(batch["image1"], batch["image2"], strict=True):
        started = time.perf_counter()
        flow_lib.estimate(image1, image2, flow_lib.DEFAULT_ESTIMATOR)
        times.append(time.perf_counter() - started)
    curve = [
        [record["step"], record["epe"]]
        for record in metrics_log.read_metrics(run_dir)
        if record.get("split") == "test" and "epe" in record
    ]
    return {
        "step": step,
        "methods": summary,
        "parameters": flow_net_lib.parameter_count(variables["params"]),
        "network_ms": latency["median_ms"],
        "dis_ms": 1e3 * float(np.median(times)) if times else None,
        "curve": curve,
    }


def flow_finetuning(runner: Runner) -> dict[str, Any]:
    """The end-point error of each flow-experiment run's flow network after depth
    training (fixed: the network as trained on the exact flow; fine-tuned: what the
    sparse depth loss made of it)."""

    data = runner.data(runner.scale.dataset)
    epe = {}
    for name in paper_suite.FLOW_EXPERIMENT[1:]:
        _, variables, _ = runner.trained(name)
        _, _, summary = flow_network.evaluate_flow(
            FlowNet(), {"params": variables["params"]["flow_net"]}, data.test
        )
        epe[name] = summary[flow_network.NETWORK]
    return {"epe": epe}


def classical(runner: Runner, dataset: str, methods: Sequence[str]) -> dict[str, Any]:

    data = runner.data(dataset)
    results = {}
    for name in methods:
        runner.print(f"{name} on {data.name}")
        method = trained_run.fit_classical(name, data.train)
        per_example, _ = evaluation.evaluate_predictor(method.predict, data.test)
        summary, abs_inv = scores(per_example)
        results[name] = {"metrics": summary, "abs_inv_per_example": abs_inv}
    return {"dataset": data.name, "methods": results}


def pose_probe(runner: Runner) -> dict[str, Any]:
    """The four settings on the main run's encoder; the pretrained two on the encoder
    of the run without the motion terms (the scratch ones are the same there)."""

    errors, arrays = {}, {}
    for index, name in enumerate(PROBED_RUNS):
        model, variables, config = runner.trained(name)
        data = runner.data(config.dataset)
        settings = encoder_pose.pose_probe_settings(
            data.train,
            data.test,
            pretrained=encoder_pose.pretrained_global_encoder(model, variables),
            steps=runner.scale.probe_steps,
            batch_size=runner.scale.batch_size,
            learning_rate=runner.scale.learning_rate,
            warmup_steps=run_configs.warmup_steps(runner.scale, runner.scale.probe_steps),
            flow_source=config.flow_source,
            seed=0,
            settings=(
                tuple(encoder_pose.POSE_PROBE_SETTINGS)
                if index == 0
                else ("pretrained_mlp", "pretrained_full")
            ),
        )
        for setting, predicted in settings.pop("predicted").items():
            arrays[f"{name}/{setting}/ids"] = np.asarray(predicted["ids"], str)
            arrays[f"{name}/{setting}/rotation"] = predicted["rotation"]
            arrays[f"{name}/{setting}/translation"] = predicted["translation"]
        errors[name] = settings
    write_npz(runner.results_dir / "pose_probe_poses.npz", **arrays)
    return {"errors": errors}


def predicted_pose(runner: Runner) -> Callable[[dict], tuple[np.ndarray, np.ndarray]]:
    """batch -> (rotation [B, 3, 3], translation [B, 3]) that the probe of
    `PREDICTED_POSE` predicts for the batch's test pairs (by id)."""
    key = "/".join(PREDICTED_POSE)
    with np.load(runner.results_dir / "pose_probe_poses.npz") as poses:
        row = {str(i): k for k, i in enumerate(poses[f"{key}/ids"])}
        rotation, translation = poses[f"{key}/rotation"], poses[f"{key}/translation"]

    def pose(batch):
        rows = [row[str(i)] for i in batch["id"]]
        return rotation[rows].astype(np.float32), translation[rows].astype(np.float32)

    return pose


def triangulation_predicted_pose(runner: Runner) -> dict[str, Any]:

    data = runner.data(runner.scale.dataset)
    pose = predicted_pose(runner)
    triangulation = classical_lib.TriangulationGtPose()

    def predict(batch):
        rotation, translation = pose(batch)
        return triangulation.predict({**batch, "rotation": rotation, "translation": translation})

    per_example, _ = evaluation.evaluate_predictor(predict, data.test)
    summary, abs_inv = scores(per_example)
    return {"metrics": summary, "abs_inv_per_example": abs_inv, "pose_of": list(PREDICTED_POSE)}


def flow_error(runner: Runner) -> dict[str, Any]:

    model, variables, config = runner.trained(MAIN_RUN)
    data = runner.data(config.dataset)
    predictors = {
        "global_local": flow_error_lib.model_predictor(model, variables),
        "triangulation_gt_pose": flow_error_lib.triangulation_predictor(),
        "triangulation_predicted_pose": flow_error_lib.triangulation_predictor(
            predicted_pose(runner)
        ),
    }
    curves = flow_error_lib.flow_error_curves(
        predictors, data.test, batch_size=runner.scale.batch_size
    )
    return {"curves": curves}


def qualitative(runner: Runner) -> dict[str, Any]:

    data = runner.data(runner.scale.dataset)
    count = min(runner.scale.figure_pairs, len(data.test))
    batch = next(
        evaluation.split_batches(
            data.test, batch_size=count, max_examples=count, all_processes=False
        )
    )
    arrays = {
        "image1": batch["image1"],
        "depth": batch["depth"],
        "depth_valid": batch["depth_valid"],
        "ids": np.asarray([str(i) for i in batch["id"]]),
    }
    # Each model at the rate its comparisons use (both rates have finished before).
    used = {name: runner.compared_run(name) for name in QUALITATIVE_RUNS}
    for name, run in used.items():
        model, variables, _ = runner.trained(run)
        arrays[name] = 1.0 / np.asarray(flow_error_lib.model_predictor(model, variables)(batch))
    write_npz(runner.results_dir / "qualitative.npz", **arrays)
    return {"runs": used, "ids": arrays["ids"]}


def filters(runner: Runner) -> dict[str, Any]:

    model, variables, config = runner.trained(MAIN_RUN)
    data = runner.data(config.dataset)
    count = min(FILTER_PAIRS, len(data.test))
    batch = next(
        evaluation.split_batches(
            data.test,
            batch_size=count,
            flow_source=config.flow_source,
            max_examples=count,
            all_processes=False,
        )
    )
    inspected = inspect_lib.inspect_pairs(variables, batch, model)
    figures = runner.results_dir / "figures"
    figures.mkdir(parents=True, exist_ok=True)
    # The first pair, the pair whose motion is most like it and the least like it.
    order = np.argsort(inspected["motion_similarity"][0, 1:])
    shown = [0, 1 + int(order[-1]), 1 + int(order[0])] if count > 2 else list(range(count))
    paths = []
    for example in shown:
        path = figures / f"filters_{example}.png"
        inspect_lib.draw_filter_banks(
            inspected["kernels"], example, path, title=f"test pair {batch['id'][example]}"
        )
        paths.append(path.name)
    return {"correlation": inspected["correlation"], "figures": paths, "pairs": count}


def regimes(runner: Runner) -> dict[str, Any]:
    """Where the main run (at its compared rate) beats the classical pipeline on the same
    flow, pair by pair: each test pair's properties (`gld.analysis.regimes`), both
    methods' Abs-Inv from their results, and the summary by property tercile."""

    run = runner.compared_run(MAIN_RUN)
    model = read_result(runner.results_dir, f"train/{run}")
    data = runner.data(runner.scale.dataset)
    classical_task = f"classical/{runner.scale.dataset.split('/')[-1]}"
    reference = read_result(runner.results_dir, classical_task)["methods"][REGIMES_REFERENCE]
    model_values = model["abs_inv_per_example"]
    reference_values = reference["abs_inv_per_example"]
    if not len(model_values) == len(reference_values) == len(data.test):
        raise RuntimeError(
            f"train/{run} scores {len(model_values)} test pairs and {classical_task} "
            f"{len(reference_values)}; {data.name} has {len(data.test)}"
        )
    config = model["config"]
    # Each result's per-pair values follow the test split's order (the evaluation's).
    examples = [
        contract.decode_example(
            data.test[index],
            flow_source=config["flow_source"],
            where=f"{data.name} test[{index}]",
        )
        for index in range(len(data.test))
    ]
    ids = [example["id"] for example in examples]
    compared = regimes_run.compare_pairs(
        examples,
        dict(zip(ids, model_values, strict=True)),
        dict(zip(ids, reference_values, strict=True)),
        model="model",
        reference="reference",
        read_texture=data.texture,
        num_bins=REGIMES_BINS,
    )
    return {
        "run": run,
        "reference": REGIMES_REFERENCE,
        "rows": compared.rows,
        "tables": {
            key: [dataclasses.asdict(summary) for summary in rows]
            for key, rows in compared.tables.items()
        },
        "correlations": compared.correlations,
        "edges": compared.edges,
    }
