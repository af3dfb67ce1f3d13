"""Evaluating a trained run, a classical method or stored depth maps, with references.

    evaluate_workdir("runs/demo", test_source, dataset="gld_scenes/small", ...)

`evaluate_workdir` evaluates a trained workdir (or a classical method, or depth maps
another system stored, `gld.evaluation.stored_predictions`) with its `REFERENCES` on the
same examples and the same flow: the dataset mean, the per-pair oracle constant and the
classical pipeline (essential matrix from the flow + triangulation), each through the
one loop of `gld.evaluation.evaluate`, and writes metrics.json, the table, per-example
CSVs and figures (`gld.evaluation.reports`) into an evaluation folder named by what was
evaluated (`evaluation_dir`); a folder holding another evaluation is refused.
"""

from __future__ import annotations

import functools
import json
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import jax
import numpy as np

from gld import contract, input_pipeline
from gld.arguments import ArgumentError
from gld.evaluation import metrics, reports, stored_predictions
from gld.evaluation.evaluate import (
    ORACLE,
    REFERENCES,
    SFM,
    STORED,
    Truth,
    evaluate_predictor,
    evaluate_source,
    split_batches,
)
from gld.files import write_problem
from gld.models import layers
from gld.models.baselines import classical
from gld.runs import workdir as workdir_lib


def fit_classical(name: str, train_source, flow_source: str = "estimated"):
    """A classical baseline by name, fitted on the training split when it needs to be.

    Raises:
      ValueError: an unknown name, or a method that needs the training split without one.
    """

    if name not in classical.CLASSICAL:
        raise ValueError(f"unknown classical method {name!r}; valid: {sorted(classical.CLASSICAL)}")
    method = classical.CLASSICAL[name]()
    if method.needs_training_data:
        if train_source is None:
            raise ValueError(f"{name} is fitted on the training split, and none was given")
        # Only the truth is read: the other fields are neither flipped nor batched.
        fit_keys = ("depth", "depth_valid")
        batches = split_batches(
            train_source,
            batch_size=16,
            flow_source=flow_source,
            keys=fit_keys,
            all_processes=False,
        )
        method.fit(
            {key: batch[key][batch["example_mask"]] for key in fit_keys} for batch in batches
        )
    return method


def _fit_reference(name: str, train_source, flow_source: str, fitted: dict[str, Any]):
    """A reference (or the evaluated classical method), fitted once: the classical
    pipeline's fallback for failed pairs is the dataset mean's value when that is fitted
    already (`SfMFlow.fit` computes the same mean), and the fixed
    `layers.INITIAL_INV_DEPTH` when there is no training split."""

    if name == SFM and "dataset_mean" in fitted:
        return classical.SfMFlow(fallback_inv_depth=fitted["dataset_mean"].inv_depth)
    if name == SFM and train_source is None:
        return classical.SfMFlow(fallback_inv_depth=layers.INITIAL_INV_DEPTH)
    return fit_classical(name, train_source, flow_source)


def on_truth(predict: Callable[[dict], dict], truth: Truth) -> Callable[[dict], dict]:
    """A predictor that reads the batch's ground truth (the per-pair oracle), given each
    example's `truth` instead: its [h, w] maps at the truth's resolution."""

    def predict_on_truth(batch: dict) -> dict[str, list[np.ndarray]]:
        maps = truth.maps([str(example_id) for example_id in batch["id"]])
        return {
            "depth": [
                np.asarray(predict({"depth": depth[None], "depth_valid": valid[None]})["depth"])[0]
                for depth, valid in maps
            ]
        }

    return predict_on_truth


def _figure_examples(source, count: int, gt_pixels: int, seed: int, flow_source: str, split: str):
    return [
        contract.prepare_example(
            source[index],
            epoch=0,
            seed=seed,
            gt_pixels=gt_pixels,
            flow_source=flow_source,
            augment=False,
            fixed_sparse_pixels=True,
            # Every field, the derived pose from the flow too (a model may read it).
            keys=[key for key in contract.CONTRACT_KEYS if key != "id"],
            where=f"{split}[{index}]",
        )
        for index in range(min(count, len(source)))
    ]


# What makes two evaluations the same one: a folder holds one of them, whatever step.
EVALUATION_IDENTITY = ("dataset", "split", "model", "flow_source", "truth_resolution", "examples")


def evaluation_dir(
    workdir: str | Path,
    *,
    split: str = "test",
    max_examples: int = 0,
    step: int | None = None,
    flow_source: str | None = None,
    truth_resolution: str = "record",
    dataset: str | None = None,
) -> Path:
    """Where an evaluation is written: <workdir>/eval for the workdir's own evaluation
    (latest checkpoint, whole test split, its own flow and dataset, the records' truth),
    else <workdir>/eval_<what differs>, e.g. eval_train_first2, eval_step500_flow-gt,
    so that an evaluation never replaces a different one."""
    parts = []
    if dataset:
        parts.append("-".join(dataset.split("/")[:2]))
    if split != "test":
        parts.append(split)
    if max_examples:
        parts.append(f"first{max_examples}")
    if step is not None:
        parts.append(f"step{step}")
    if flow_source:
        parts.append(f"flow-{flow_source}")
    if truth_resolution != "record":
        parts.append(f"truth-{truth_resolution}")
    return Path(workdir) / "_".join(["eval", *parts])


def _same_dataset(evaluated: str, trained: str) -> bool:
    """Whether 'name/config[/version]' names the dataset a run was trained on."""
    return not evaluated or not trained or evaluated.split("/")[:2] == trained.split("/")[:2]


def _check_identity(out_dir: Path, info: dict[str, Any]) -> None:
    """Refuses to write over an evaluation of something else (another dataset, say)."""
    path = out_dir / "metrics.json"
    if not path.exists():
        return
    stored = json.loads(path.read_text())
    differing = {
        key: (stored.get(key), info.get(key))
        for key in EVALUATION_IDENTITY
        if key in stored and stored.get(key) != info.get(key)
    }
    if differing:
        details = ", ".join(
            f"{k}: {old!r} there vs {new!r} now" for k, (old, new) in differing.items()
        )
        raise ValueError(
            f"{out_dir} holds a different evaluation ({details}); it is kept: evaluate into "
            "another --workdir"
        )


def _check_writable(out_dir: Path) -> None:
    """Refuses, before anything is evaluated, a folder the report could not be written in."""
    problem = write_problem(out_dir) if jax.process_index() == 0 else None
    if problem:
        raise ArgumentError(f"the evaluation would be written to {out_dir}: {problem}")


def evaluate_workdir(
    workdir: str | Path,
    source,
    *,
    train_source=None,
    dataset: str = "",
    height: int,
    width: int,
    split: str = "test",
    num_figures: int = 8,
    with_dataset_mean: bool = True,
    with_oracle: bool = True,
    with_sfm_flow: bool = True,
    batch_size: int = 16,
    max_examples: int = 0,
    step: int | None = None,
    classical_method: str | None = None,
    predictions: stored_predictions.StoredPredictions | None = None,
    flow_source: str | None = None,
    truth: Truth | None = None,
    records_protocol: Mapping[str, Any] | None = None,
    protocol_note: str = "",
    print_fn: Callable[[str], None] = print,
) -> dict[str, Any]:
    """Evaluates a workdir's trained model (or a classical method, or stored predictions)
    on `source`.

    Writes <workdir>/eval (`gld.evaluation.reports`). The `REFERENCES` are evaluated alongside on
    the same examples with the same flow (the workdir's unless `flow_source` is given),
    each when asked and unless it is the evaluated method itself: the dataset mean
    (fitted on `train_source`, so only when it is given), the per-pair oracle constant
    and the classical pipeline `sfm_flow` (pose and depth from the flow alone; its
    failed pairs fall back to the dataset mean, or to `layers.INITIAL_INV_DEPTH` without
    `train_source`, which metrics.json records). Rows: the method (`STORED` for
    `predictions`), then dataset_mean, oracle_pair_median, sfm_flow. The references are
    host-side methods: process 0 evaluates them, on every example.

    A folder already holding this evaluation (same `EVALUATION_IDENTITY`, whatever its
    references) is rewritten with this run's rows only (`reports.write_report`).

    Every method is scored against the records' ground truth at (height, width), or,
    with `truth`, against the truth it looks up by id (`score_against_truth`; stored
    predictions are then resized straight to each truth's resolution, and the oracle
    takes its constant from that truth); the stamp says which. `records_protocol`, the
    build options that make the records' protocol (a DeMoN dataset's WebP decoder, depth
    resampling and order), and `protocol_note`, a clause of the caller's, are named in the
    stamp and in metrics.json (`reports.write_report`).

    Raises:
      FileNotFoundError, ValueError: `truth` cannot serve an example, or `predictions`
        lack a file or hold a bad one (`StoredPredictions.check`), before anything is
        evaluated or written.
      gld.arguments.ArgumentError: the evaluation folder cannot be written in (a
        read-only workdir), before anything is evaluated.
    """
    results = {}
    fitted: dict[str, Any] = {}
    examples_count = min(max_examples, len(source)) if max_examples else len(source)
    info = {"dataset": dataset, "split": split, "examples": examples_count}
    if truth is not None or predictions is not None:
        examples = stored_predictions.record_ids_and_baselines(
            input_pipeline.first_records(source, max_examples)
        )
    file_resolutions = None
    if truth is not None:
        truth.check(examples)
        file_resolutions = metrics.resolution_counts(truth.shapes().values())
        info.update(truth_resolution="file", truth_resolutions=file_resolutions)
        info.update(truth.summary())
    else:
        info["truth_resolution"] = "record"

    def host_predictor(method_name: str, predict: Callable) -> Callable:
        return on_truth(predict, truth) if truth is not None and method_name == ORACLE else predict

    if classical_method or predictions is not None:
        flow_source = flow_source or "estimated"
        if predictions is not None:
            method, name = predictions, STORED
            predictions.check(
                examples,
                height=height,
                width=width,
                shapes=truth.shapes() if truth is not None else None,
            )
            protocol_note = "; ".join(filter(None, [predictions.protocol_note(), protocol_note]))
            info.update(predictions.summary())
        else:
            method = _fit_reference(classical_method, train_source, flow_source, fitted)
            fitted[classical_method] = method
            name = classical_method
        out_dir = evaluation_dir(
            workdir,
            split=split,
            max_examples=max_examples,
            step=step,
            flow_source=None if flow_source == "estimated" else flow_source,
            truth_resolution=info["truth_resolution"],
        )
        _check_identity(out_dir, {**info, "model": name, "flow_source": flow_source})
        _check_writable(out_dir)
        predict = host_predictor(name, method.predict)
        results[name] = evaluate_predictor(
            predict,
            source,
            batch_size=batch_size,
            flow_source=flow_source,
            max_examples=max_examples,
            progress=True,
            truth=truth,
        )
        predict_depth = lambda batch: predict(batch)["depth"]  # noqa: E731
        gt_pixels, seed = 1, 0
        info.update(model=name, flow_source=flow_source)
    else:
        model, variables, config, restored_step = workdir_lib.restore_trained(workdir, step=step)
        own_flow, flow_source = (
            flow_source in (None, config.flow_source),
            flow_source or config.flow_source,
        )
        out_dir = evaluation_dir(
            workdir,
            split=split,
            max_examples=max_examples,
            step=step,
            flow_source=None if own_flow else flow_source,
            truth_resolution=info["truth_resolution"],
            dataset=None if _same_dataset(dataset, config.dataset) else dataset,
        )
        _check_identity(out_dir, {**info, "model": config.model, "flow_source": flow_source})
        _check_writable(out_dir)
        results[config.model] = evaluate_source(
            model,
            variables,
            source,
            batch_size=batch_size,
            flow_source=flow_source,
            max_examples=max_examples,
            progress=True,
            truth=truth,
        )
        apply = jax.jit(functools.partial(layers.apply_model, model))
        input_keys = layers.input_keys(model)
        predict_depth = lambda batch: apply(  # noqa: E731
            variables, {key: batch[key] for key in input_keys}
        )["depth"]
        gt_pixels, seed = config.gt_pixels, config.seed
        # The step restored: the newest intact checkpoint unless one was asked for.
        info.update(
            model=config.model,
            gt_pixels=config.gt_pixels,
            flow_source=flow_source,
            step=int(restored_step),
        )
    wanted = {
        "dataset_mean": with_dataset_mean and train_source is not None,
        ORACLE: with_oracle,
        SFM: with_sfm_flow,
    }
    references = [name for name in REFERENCES if wanted[name] and name != info["model"]]
    for reference in references if jax.process_index() == 0 else []:
        fitted[reference] = _fit_reference(reference, train_source, flow_source, fitted)
        results[reference] = evaluate_predictor(
            host_predictor(reference, fitted[reference].predict),
            source,
            batch_size=batch_size,
            flow_source=flow_source,
            max_examples=max_examples,
            truth=truth,
        )
    if "dataset_mean" in results:
        info["dataset_mean_inv_depth"] = fitted["dataset_mean"].inv_depth
    if SFM in results:
        info["sfm_flow_fallback_inv_depth"] = fitted[SFM].fallback_inv_depth
        info["sfm_flow_fallback"] = (
            "the training split's mean inverse depth"
            if train_source is not None
            else "a fixed constant (no training split)"
        )
    if jax.process_index() != 0:
        return {}
    report = reports.write_report(
        out_dir,
        results,
        height=height,
        width=width,
        info=info,
        protocol_note=protocol_note,
        truth_resolution=info["truth_resolution"],
        file_resolutions=file_resolutions,
        records_protocol=records_protocol,
    )
    if num_figures:
        evaluated = input_pipeline.first_records(source, max_examples)
        examples = _figure_examples(evaluated, num_figures, gt_pixels, seed, flow_source, split)
        batch = {
            key: np.stack([example[key] for example in examples])
            for key, value in examples[0].items()
            if isinstance(value, np.ndarray)
        }
        batch["id"] = np.array([example["id"] for example in examples])
        # Drawn at the records' resolution, next to the records' truth.
        depth_maps = [
            metrics.resize_nearest(np.asarray(depth), height, width)
            for depth in predict_depth(batch)
        ]
        reports.render_examples(out_dir / "figures", examples, depth_maps)
    print_fn((out_dir / "table.md").read_text())
    return report
