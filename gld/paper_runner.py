"""Runs a suite of `gld.paper_suite`: trains, reuses, resumes and scores every run, then
the analyses; each result is a file, so a killed suite continues where it stopped.

    <workdir>/runs/<run>/            each training run's workdir (gld.workdir)
    <workdir>/results/<task>.json    one result per task, written atomically when done
    <workdir>/results/<task>.npz     arrays a later task or the report reads

Tasks, in order: every training run (`train/<run>`: train or resume, then evaluate on
the test split), the classical references on each dataset (`classical/<dataset>`), the
pose probe (`pose_probe`), triangulation with the probe's pose
(`triangulation_predicted_pose`), the flow-error curves (`flow_error`), the qualitative
predictions (`qualitative`) and the generated filters (`filters`). A task is skipped when
its result exists and was made with the same configuration; a training run whose result
is missing resumes from its newest checkpoint. `gld.paper_report` turns the results into
the report.
"""

from __future__ import annotations

import dataclasses
import json
import os
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from gld import paper_suite
from gld.paper_suite import Run, Scale

# Classical methods of the main dataset, and of the varying-intrinsics one.
CLASSICAL = ("dataset_mean", "oracle_pair_median", "triangulation_gt_pose", "sfm_flow")
CLASSICAL_VARYING = ("dataset_mean", "oracle_pair_median", "sfm_flow")

# Seconds per training step at 128x96, batch 16, on the 2-core CPU machine
# (`python -m experiments.benchmark --height=96 --width=128 --models=...`), for the ETA.
STEP_SECONDS = {"global_local": 0.2, "small_encdec": 0.4, "eigen": 0.46, "dispnet": 5.7}
DEFAULT_STEP_SECONDS = 5.0


@dataclasses.dataclass(frozen=True)
class Data:
    """A built dataset's splits, as the runner needs them."""

    name: str  # TFDS full name
    train: Any  # random-access record sources
    test: Any
    height: int
    width: int


@dataclasses.dataclass(frozen=True)
class Task:
    name: str
    run: Callable[[], dict[str, Any]]
    identity: dict[str, Any]  # what the result depends on; a changed one redoes the task
    seconds: float  # estimated, for the suite's ETA
    needs: tuple[str, ...] = ()


def result_path(workdir: Path, task: str) -> Path:
    return Path(workdir) / "results" / f"{task.replace('/', '__')}.json"


def read_result(workdir: str | Path, task: str) -> dict[str, Any] | None:
    """A task's result, or None if it has not finished."""
    path = result_path(Path(workdir), task)
    if not path.exists():
        return None
    return json.loads(path.read_text())


def _write_json(path: Path, content: dict[str, Any]) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    temporary = path.with_name(f".{path.name}.tmp")
    temporary.write_text(json.dumps(content, indent=1, default=_plain) + "\n")
    os.replace(temporary, path)


def _write_npz(path: Path, **arrays: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    temporary = path.with_name(f".{path.stem}.tmp.npz")
    np.savez(temporary, **arrays)
    os.replace(temporary, path)


def _plain(value: Any) -> Any:
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    raise TypeError(f"not JSON serialisable: {type(value)}")


def _summary(per_example: dict[str, np.ndarray]) -> tuple[dict[str, dict], np.ndarray]:
    from gld import metrics

    per_example = dict(per_example)
    mask = per_example.pop("example_mask").astype(bool)
    return metrics.summarise(per_example, mask), np.asarray(per_example["abs_inv"])[mask]


def _curves(run_dir: Path) -> dict[str, list[list[float]]]:
    """The training loss on the supervised pixels and the test Abs-Inv, by step."""
    curves: dict[str, list[list[float]]] = {"train": [], "test": []}
    path = run_dir / "metrics.jsonl"
    if not path.exists():
        return curves
    for line in path.read_text().splitlines():
        record = json.loads(line)
        if record.get("split") == "train" and "depth_l1" in record:
            curves["train"].append([record["step"], record["depth_l1"]])
        elif record.get("split") == "test" and "abs_inv" in record:
            curves["test"].append([record["step"], record["abs_inv"]])
    return curves


class SuiteRunner:
    """Builds a suite's tasks and runs those not done yet.

    Args:
      scale: the suite.
      workdir: where runs and results go.
      data: dataset name -> its `Data` (built on first use by the caller).
      print_fn: progress messages.
      progress: training progress bars.
    """

    def __init__(
        self,
        scale: Scale,
        workdir: str | Path,
        data: Callable[[str], Data],
        *,
        print_fn: Callable[[str], None] = print,
        progress: bool = True,
    ):
        self.scale = scale
        self.workdir = Path(workdir)
        self._data = data
        self._loaded: dict[str, Data] = {}
        self.print = print_fn
        self.progress = progress
        self.runs = {run.name: run for run in paper_suite.suite_runs(scale)}

    def data(self, dataset: str) -> Data:
        if dataset not in self._loaded:
            self._loaded[dataset] = self._data(dataset)
        return self._loaded[dataset]

    def run_dir(self, name: str) -> Path:
        return self.workdir / "runs" / name

    def _config(self, run: Run):
        data = self.data(self.scale.varying_dataset if run.varying else self.scale.dataset)
        return paper_suite.run_config(self.scale, run, height=data.height, width=data.width)

    # -- tasks --------------------------------------------------------------------------

    def tasks(self) -> list[Task]:
        """Every task of the suite, in order."""
        tasks = []
        for run in self.runs.values():
            steps = paper_suite.run_steps(self.scale, run)
            seconds = steps * STEP_SECONDS.get(run.model, DEFAULT_STEP_SECONDS) + 30
            tasks.append(
                Task(
                    f"train/{run.name}",
                    lambda run=run: self._train(run),
                    {"run": dataclasses.asdict(run), "scale": self.scale.name, "steps": steps},
                    seconds,
                )
            )
        for dataset, methods in (
            (self.scale.dataset, CLASSICAL),
            (self.scale.varying_dataset, CLASSICAL_VARYING),
        ):
            tasks.append(
                Task(
                    f"classical/{dataset.split('/')[-1]}",
                    lambda dataset=dataset, methods=methods: self._classical(dataset, methods),
                    {"dataset": dataset, "methods": list(methods)},
                    60,
                )
            )
        main = "global_local_1px"
        tasks += [
            Task(
                "pose_probe",
                self._pose_probe,
                {"steps": self.scale.probe_steps, "encoder_of": main},
                4 * self.scale.probe_steps * 0.1 + 60,
                needs=(f"train/{main}",),
            ),
            Task(
                "triangulation_predicted_pose",
                self._triangulation_predicted_pose,
                {"pose_of": "pretrained_full"},
                30,
                needs=("pose_probe",),
            ),
            Task(
                "flow_error",
                self._flow_error,
                {"model": main, "pose_of": "pretrained_full"},
                60,
                needs=(f"train/{main}", "pose_probe"),
            ),
            Task(
                "qualitative",
                self._qualitative,
                {"pairs": self.scale.figure_pairs},
                60,
                needs=tuple(f"train/{name}" for name in QUALITATIVE_RUNS),
            ),
            Task("filters", self._filters, {"model": main}, 20, needs=(f"train/{main}",)),
        ]
        return tasks

    def selected(self, only: Sequence[str] | None = None) -> list[Task]:
        """The tasks named in `only` (a task's name, or a group: "train", "classical"),
        or all; ValueError naming any name that matches no task."""
        tasks = self.tasks()
        if not only:
            return tasks
        names = [task.name for task in tasks]
        unknown = [n for n in only if not any(_matches(t, n) for t in names)]
        if unknown:
            raise ValueError(f"unknown suite tasks {unknown}; valid: {names}")
        return [t for t in tasks if any(_matches(t.name, n) for n in only)]

    def finished(self) -> dict[str, dict[str, Any]]:
        """The results of every finished task, by task name."""
        results = {}
        for task in self.tasks():
            result = read_result(self.workdir, task.name)
            if result is not None:
                results[task.name] = result
        return results

    def run(self, only: Sequence[str] | None = None) -> dict[str, dict[str, Any]]:
        """Runs every task not done yet (those named in `only`, if given; see `selected`);
        returns the results of every finished task."""
        import jax

        tasks = self.selected(only)
        pending = [task for task in tasks if not self._done(task)]
        for task in tasks:
            if task not in pending:
                self.print(f"{task.name}: done (reused {result_path(self.workdir, task.name)})")
        spent, estimated = 0.0, 0.0
        for index, task in enumerate(pending):
            remaining = sum(t.seconds for t in pending[index:])
            pace = spent / estimated if estimated else 1.0
            self.print(
                f"[{index + 1}/{len(pending)}] {task.name} — suite ETA "
                f"{_duration(remaining * pace)}"
            )
            missing = [need for need in task.needs if read_result(self.workdir, need) is None]
            if missing:
                self.print(f"{task.name}: skipped, needs {missing} first")
                continue
            started = time.perf_counter()
            result = task.run()
            seconds = time.perf_counter() - started
            result.update(task=task.name, identity=task.identity, seconds=seconds)
            if jax.process_index() == 0:
                _write_json(result_path(self.workdir, task.name), result)
            spent += seconds
            estimated += task.seconds
        return self.finished()

    def _done(self, task: Task) -> bool:
        result = read_result(self.workdir, task.name)
        return result is not None and result.get("identity") == json.loads(
            json.dumps(task.identity, default=_plain)
        )

    def _train(self, run: Run) -> dict[str, Any]:
        from gld import evaluation, train
        from gld import model as model_lib
        from gld import workdir as workdir_lib

        config = self._config(run)
        data = self.data(config.dataset)
        run_dir = self.run_dir(run.name)
        self.print(f"{run.name}: {config.steps} steps of {run.model} in {run_dir}")
        train.train_and_evaluate(
            config,
            run_dir,
            data.train,
            data.test if config.eval_every else None,
            progress=self.progress,
            print_fn=self.print,
        )
        model, variables, saved = workdir_lib.load_trained(run_dir)
        per_example, _ = evaluation.evaluate_source(
            model,
            variables,
            data.test,
            batch_size=saved.eval_batch_size,
            flow_source=saved.flow_source,
        )
        summary, abs_inv = _summary(per_example)
        return {
            "run": run.name,
            "model": run.model,
            "label": run.label,
            "dataset": data.name,
            "config": dataclasses.asdict(config),
            "parameters": model_lib.parameter_counts(variables["params"])["total"],
            "metrics": summary,
            "abs_inv_per_example": abs_inv,
            "curves": _curves(run_dir),
            "train_seconds": _train_seconds(run_dir),
        }

    def _classical(self, dataset: str, methods: Sequence[str]) -> dict[str, Any]:
        from gld import evaluation

        data = self.data(dataset)
        results = {}
        for name in methods:
            self.print(f"{name} on {data.name}")
            method = evaluation.fit_classical(name, data.train)
            per_example, _ = evaluation.evaluate_predictor(method.predict, data.test)
            summary, abs_inv = _summary(per_example)
            results[name] = {"metrics": summary, "abs_inv_per_example": abs_inv}
        return {"dataset": data.name, "methods": results}

    def _pose_probe(self) -> dict[str, Any]:
        from gld import probes
        from gld import workdir as workdir_lib

        model, variables, config = workdir_lib.load_trained(self.run_dir("global_local_1px"))
        data = self.data(config.dataset)
        pretrained = probes.pretrained_global_encoder(model, variables)
        settings = probes.pose_probe_settings(
            data.train,
            data.test,
            pretrained=pretrained,
            steps=self.scale.probe_steps,
            batch_size=self.scale.batch_size,
            learning_rate=self.scale.learning_rate,
            warmup_steps=paper_suite.warmup_steps(self.scale, self.scale.probe_steps),
            flow_source=config.flow_source,
            seed=0,
        )
        poses = settings.pop("predicted")
        arrays = {}
        for setting, predicted in poses.items():
            arrays[f"{setting}/ids"] = np.asarray(predicted["ids"], str)
            arrays[f"{setting}/rotation"] = predicted["rotation"]
            arrays[f"{setting}/translation"] = predicted["translation"]
        _write_npz(self.workdir / "results" / "pose_probe_poses.npz", **arrays)
        return {"errors": settings}

    def _predicted_poses(self, setting: str) -> dict[str, tuple[np.ndarray, np.ndarray]]:
        with np.load(self.workdir / "results" / "pose_probe_poses.npz") as poses:
            ids = poses[f"{setting}/ids"]
            rotation, translation = poses[f"{setting}/rotation"], poses[f"{setting}/translation"]
        return {str(i): (rotation[k], translation[k]) for k, i in enumerate(ids)}

    def _with_predicted_pose(self, batch: dict, poses) -> dict:
        batch = dict(batch)
        ids = [str(i) for i in batch["id"]]
        batch["rotation"] = np.stack([poses[i][0] for i in ids]).astype(np.float32)
        batch["translation"] = np.stack([poses[i][1] for i in ids]).astype(np.float32)
        return batch

    def _triangulation_predicted_pose(self) -> dict[str, Any]:
        from gld import evaluation
        from gld.baselines import classical

        data = self.data(self.scale.dataset)
        poses = self._predicted_poses("pretrained_full")
        triangulation = classical.TriangulationGtPose()
        per_example, _ = evaluation.evaluate_predictor(
            lambda batch: triangulation.predict(self._with_predicted_pose(batch, poses)),
            data.test,
        )
        summary, abs_inv = _summary(per_example)
        return {"metrics": summary, "abs_inv_per_example": abs_inv, "pose_of": "pretrained_full"}

    def _flow_error(self) -> dict[str, Any]:
        from gld import flow_error
        from gld import workdir as workdir_lib

        model, variables, config = workdir_lib.load_trained(self.run_dir("global_local_1px"))
        data = self.data(config.dataset)
        poses = self._predicted_poses("pretrained_full")

        def predicted_pose(batch):
            posed = self._with_predicted_pose(batch, poses)
            return posed["rotation"], posed["translation"]

        predictors = {
            "global_local": flow_error.model_predictor(model, variables),
            "triangulation_gt_pose": flow_error.triangulation_predictor(),
            "triangulation_predicted_pose": flow_error.triangulation_predictor(predicted_pose),
        }
        curves = flow_error.flow_error_curves(
            predictors, data.test, batch_size=self.scale.batch_size
        )
        return {"curves": curves}

    def _qualitative(self) -> dict[str, Any]:
        import jax

        from gld import evaluation, layers
        from gld import workdir as workdir_lib

        data = self.data(self.scale.dataset)
        count = min(self.scale.figure_pairs, len(data.test))
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
        for name in QUALITATIVE_RUNS:
            model, variables, _ = workdir_lib.load_trained(self.run_dir(name))
            keys = layers.input_keys(model)
            outputs = jax.jit(lambda b, m=model, v=variables: layers.apply_model(m, v, b))(
                {k: batch[k] for k in keys}
            )
            arrays[name] = np.asarray(outputs["inv_depth"])
        _write_npz(self.workdir / "results" / "qualitative.npz", **arrays)
        return {"runs": list(QUALITATIVE_RUNS), "ids": arrays["ids"]}

    def _filters(self) -> dict[str, Any]:
        from gld import evaluation
        from gld import filter_inspection as inspect_lib
        from gld import workdir as workdir_lib

        model, variables, config = workdir_lib.load_trained(self.run_dir("global_local_1px"))
        data = self.data(config.dataset)
        count = min(16, len(data.test))
        batch = next(
            evaluation.split_batches(
                data.test, batch_size=count, max_examples=count, all_processes=False
            )
        )
        inspected = inspect_lib.filter_banks(variables, batch, model=model)
        rotation, translation = inspect_lib.rotation_translation_of(batch)
        filter_sim = inspect_lib.filter_similarity(inspected["kernels"], inspected["biases"])
        motion_sim = inspect_lib.motion_similarity(rotation, translation)
        correlation = inspect_lib.similarity_correlation(filter_sim, motion_sim)
        figures = self.workdir / "results" / "figures"
        figures.mkdir(parents=True, exist_ok=True)
        # The most and the least similar motions among the pairs, to compare their banks.
        order = np.argsort(motion_sim[0, 1:])
        shown = [0, 1 + int(order[-1]), 1 + int(order[0])] if count > 2 else list(range(count))
        paths = []
        for example in shown:
            path = figures / f"filters_{example}.png"
            inspect_lib.draw_filter_banks(
                inspected["kernels"], example, path, title=f"test pair {batch['id'][example]}"
            )
            paths.append(path.name)
        return {"similarity_correlation": correlation, "figures": paths, "pairs": count}


# The qualitative grid's columns (besides image and truth), in order.
QUALITATIVE_RUNS = ("small_encdec_1px", "dispnet_1px", "global_local_1px")


def _matches(task: str, name: str) -> bool:
    """Whether `name` selects `task`: its whole name, or a leading group of it."""
    return task == name or task.startswith(name.rstrip("/") + "/")


def _train_seconds(run_dir: Path) -> float | None:
    """Seconds of training, from the metrics log's step rates (over every launch)."""
    path = run_dir / "metrics.jsonl"
    if not path.exists():
        return None
    seconds, previous = 0.0, 0
    for line in path.read_text().splitlines():
        record = json.loads(line)
        if record.get("split") == "train" and record.get("steps_per_sec"):
            seconds += (record["step"] - previous) / record["steps_per_sec"]
            previous = record["step"]
    return seconds


def _duration(seconds: float) -> str:
    minutes = round(seconds / 60)
    return f"{minutes // 60} h {minutes % 60:02d} min" if minutes >= 60 else f"{minutes} min"
