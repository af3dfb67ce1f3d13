"""Runs a suite of `gld.paper.suite`: trains, reuses, resumes and scores every run, then
the analyses (`gld.paper.analyses`: what each computes); each result is a file, so a
killed suite continues where it stopped.

    <workdir>/runs/<run>/        each training run's workdir (gld.runs.workdir)
    <results>/<task>.json        one result per task, written atomically when done
    <results>/<task>.npz         arrays a later task or the report reads

Tasks, in order: the classical references on each dataset (`classical/<dataset>`, a
minute each: the main table's reference rows come first), then every training run of
the paper's main experiments (`train/<run>`: train or resume, then evaluate on the test
split) in the order of `paper_suite.suite_runs`, each analysis as soon as the runs it
reads have finished: the generated filters (`filters`), the qualitative predictions
(`qualitative`), the pose probe (`pose_probe`), triangulation with the probe's pose
(`triangulation_predicted_pose`), the flow-error curves (`flow_error`); then the paper's
remaining comparisons: the learned flow network (`flow_net`: trained on the exact flow,
its end-point error and speed against DIS), the self-supervised and flow experiment's
runs, and the flow networks' end-point error after depth training (`flow_finetuning`).
A task is skipped when its result exists and was made with the same configuration; a
training run whose result is missing resumes from its newest checkpoint. The results
directory can travel without the runs (the launcher keeps it beside the report): an
analysis whose run has a result but no checkpoint here retrains that run with the same
configuration and seed, and checks whether it scores what its result says (the
analysis's result notes it if not).
`gld.paper.report` turns the results into the report.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from gld import files as files_lib
from gld.evaluation import evaluate as evaluation
from gld.evaluation import flow_network
from gld.models import registry
from gld.paper import analyses
from gld.paper import suite as paper_suite
from gld.paper.suite import Run, Scale
from gld.runs import metrics_log, trained_flow
from gld.runs import workdir as workdir_lib
from gld.training import flow_trainer as flow_training
from gld.training import trainer as train

# Seconds per training step at 128x96, batch 16, on the 2-core CPU machine (the cpu
# suite's runs, evaluations included; `experiments.benchmark` times the bare steps), and
# of a pose-probe step: for the ETA only.
STEP_SECONDS = {
    "global_local": 0.27,
    "small_encdec": 0.45,
    "eigen": 0.5,
    "dispnet": 6.0,
    "fcrn": 5.0,
    "struct2depth": 0.6,
    "struct2depth_flow": 0.6,
    "global_local_flow_net": 0.55,
    "flow_net_head": 0.65,
    "pose_probe": 0.1,
    "flow_net": 0.21,
}
DEFAULT_STEP_SECONDS = 5.0

# The runs trained after the main experiments' analyses: the paper's remaining
# comparisons (the first of them and every later run).
FIRST_REMAINING_RUN = "struct2depth"


def step_seconds(model: str) -> float:
    return STEP_SECONDS.get(model, DEFAULT_STEP_SECONDS)


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


def result_path(results_dir: str | Path, task: str) -> Path:
    return Path(results_dir) / f"{task.replace('/', '__')}.json"


def read_result(results_dir: str | Path, task: str) -> dict[str, Any] | None:
    """A task's result, or None if it has not finished."""
    path = result_path(results_dir, task)
    if not path.exists():
        return None
    return json.loads(path.read_text())


def _write_json(path: Path, content: dict[str, Any]) -> None:

    path.parent.mkdir(parents=True, exist_ok=True)
    files_lib.write_atomically(path, json.dumps(content, indent=1, default=_plain) + "\n")


def _config_identity(config) -> dict[str, Any]:
    """A training run's identity: its whole configuration but the resolution, which the
    dataset fixes."""
    values = dataclasses.asdict(config)
    values.pop("height"), values.pop("width")
    return values


def _same_identity(result: dict[str, Any], task: Task) -> bool:
    return result.get("identity") == json.loads(json.dumps(task.identity, default=_plain))


def _checkpointed_step(run_dir: Path) -> int:
    """The newest checkpoint's step of a run directory (0 without one)."""
    steps = [int(p.name) for p in (run_dir / "checkpoints").glob("*") if p.name.isdigit()]
    return max(steps, default=0)


def _other_configuration(run_dir: Path, config) -> dict[str, Any]:
    """The options in which a run directory's training differs from `config` ({} when it
    holds none or the same)."""

    try:
        return workdir_lib.check_run_config(run_dir, config) or {}
    except ValueError as error:
        return {"architecture, dataset or resolution": str(error)}


def _plain(value: Any) -> Any:
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    raise TypeError(f"not JSON serialisable: {type(value)}")


def _training_log(run_dir: Path) -> tuple[dict[str, list[list[float]]], float | None]:
    """From a run's metrics log: the training loss on the supervised pixels, the gradient
    norm and the test Abs-Inv by step, and the seconds of training (from the step rates,
    over every launch; None without a log)."""

    records = metrics_log.read_metrics(run_dir)
    curves: dict[str, list[list[float]]] = {"train": [], "loss": [], "grad_norm": [], "test": []}
    seconds, previous = 0.0, 0
    for record in records:
        if record.get("split") == "train":
            if "depth_l1" in record:
                curves["train"].append([record["step"], record["depth_l1"]])
            for key in ("loss", "grad_norm"):
                if key in record:
                    curves[key].append([record["step"], record[key]])
            if record.get("steps_per_sec"):
                seconds += (record["step"] - previous) / record["steps_per_sec"]
                previous = record["step"]
        elif record.get("split") == "test" and "abs_inv" in record:
            curves["test"].append([record["step"], record["abs_inv"]])
    return curves, (seconds if records else None)


class SuiteRunner:
    """Builds a suite's tasks and runs those not done yet.

    Args:
      scale: the suite.
      workdir: where the training runs go.
      data: dataset name -> its `Data` (built on first use by the caller).
      results_dir: where the results go (default: <workdir>/results).
      print_fn: progress messages.
      progress: training progress bars.
      dataset_version: the version of a dataset by name (e.g. "2.0.0"), which then enters
        the identity of every task that reads it: a result made on another version of the
        data is redone, never reused (None leaves versions out of the identities).
    """

    def __init__(
        self,
        scale: Scale,
        workdir: str | Path,
        data: Callable[[str], Data],
        *,
        results_dir: str | Path | None = None,
        print_fn: Callable[[str], None] = print,
        progress: bool = True,
        dataset_version: Callable[[str], str] | None = None,
    ):
        self.scale = scale
        self._dataset_version = dataset_version
        self.workdir = Path(workdir)
        self.results_dir = (
            Path(results_dir) if results_dir is not None else self.workdir / "results"
        )
        self._data = data
        self._loaded: dict[str, Data] = {}
        self.print = print_fn
        self.progress = progress
        self.runs = {run.name: run for run in paper_suite.suite_runs(scale)}
        self._differences: list[str] = []  # retrained runs that score otherwise

    def data(self, dataset: str) -> Data:
        if dataset not in self._loaded:
            self._loaded[dataset] = self._data(dataset)
        return self._loaded[dataset]

    def _version_of(self, dataset: str) -> dict[str, str]:
        """{"dataset_version": ...} of a dataset when the runner was told versions: a
        result of another version of the data is not this suite's (empty otherwise)."""
        if self._dataset_version is None:
            return {}
        return {"dataset_version": self._dataset_version(dataset)}

    def run_dir(self, name: str) -> Path:
        return self.workdir / "runs" / name

    def _rated(self, run: Run) -> Run | None:
        """The run at the rate its model's learning-rate check chose
        (`gld.paper.suite.with_compared_rate`); None until that check has finished."""
        return paper_suite.with_compared_rate(
            self.scale, run, lambda n: read_result(self.results_dir, f"train/{n}")
        )

    def _config(self, run: Run, size: tuple[int, int] | None = None):
        """The run's configuration at `size` (height, width); by default its dataset's."""
        rated = self._rated(run)
        if rated is None:
            raise RuntimeError(
                f"{run.name}: the learning-rate check of {run.rate_of} has not finished"
            )
        run = rated
        if size is None:
            data = self.data(self.scale.varying_dataset if run.varying else self.scale.dataset)
            size = (data.height, data.width)
        return paper_suite.run_config(
            self.scale,
            run,
            height=size[0],
            width=size[1],
            flow_net_workdir=str(self.flow_net_dir()),
        )

    def compared_run(self, name: str) -> str:
        """The run of a main-table model that its comparisons use
        (`gld.paper.suite.compared_run`); both of its runs have finished."""
        run = paper_suite.compared_run(
            self.scale, name, lambda n: read_result(self.results_dir, f"train/{n}")
        )
        if run is None:
            raise RuntimeError(f"{name}: its learning-rate check has not finished")
        return run

    def flow_net_dir(self) -> Path:
        return self.workdir / "runs" / "flow_net"

    # -- tasks --------------------------------------------------------------------------

    def tasks(self) -> list[Task]:
        """Every task of the suite, in order. A task's identity is what its result depends
        on: a training run's whole configuration; an analysis's options and the
        identities of the results it reads."""
        tasks: list[Task] = []
        identities: dict[str, dict[str, Any]] = {}

        def add(name, run, identity, seconds, needs=(), inputs=None):
            # `inputs`: the needs whose identities are this task's too (default: all).
            inputs = needs if inputs is None else inputs
            identity = {**identity, "inputs": {need: identities[need] for need in inputs}}
            identities[name] = identity
            tasks.append(Task(name, run, identity, seconds, tuple(needs)))

        def add_runs(runs, then):
            for run in runs:
                # A flow network's run enters by the identity of the `flow_net` task.
                needs = ["flow_net"] if run.model in paper_suite.FLOW_NET_MODELS else []
                rated = self._rated(run)
                config = paper_suite.run_config(
                    self.scale, rated or run, height=0, width=0, flow_net_workdir="<flow_net>"
                )
                identity = _config_identity(config) | self._version_of(config.dataset)
                inputs = list(needs)
                if run.rate_of is not None:
                    # Its rate is its model's compared one: the check's runs come first,
                    # and its identity holds the rate they chose (a placeholder before).
                    needs += [f"train/{n}" for n in paper_suite.rate_runs(self.scale, run.rate_of)]
                    if rated is None:
                        identity["learning_rate"] = f"the compared rate of {run.rate_of}"
                add(
                    f"train/{run.name}",
                    lambda run=run: self._train(run),
                    identity,
                    paper_suite.run_steps(self.scale, run) * step_seconds(run.model) + 30,
                    needs=needs,
                    inputs=inputs,
                )
                then()

        for dataset in (self.scale.dataset, self.scale.varying_dataset):
            add(
                f"classical/{dataset.split('/')[-1]}",
                lambda dataset=dataset: analyses.classical(self, dataset, analyses.CLASSICAL),
                {"dataset": dataset, "methods": list(analyses.CLASSICAL)}
                | self._version_of(dataset),
                60,
            )
        probe = {
            "steps": self.scale.probe_steps,
            "batch_size": self.scale.batch_size,
            "learning_rate": self.scale.learning_rate,
        }
        # The analyses, each made as soon as the runs it reads have finished (their
        # checkpoints are then at hand; where they are not, `trained` retrains them).
        waiting = [
            (
                "filters",
                functools.partial(analyses.filters, self),
                {"pairs": analyses.FILTER_PAIRS},
                20,
                [f"train/{analyses.MAIN_RUN}"],
            ),
            (
                "qualitative",
                functools.partial(analyses.qualitative, self),
                {"pairs": self.scale.figure_pairs},
                60,
                [
                    f"train/{run}"
                    for name in analyses.QUALITATIVE_RUNS
                    for run in paper_suite.rate_runs(self.scale, name)
                ],
            ),
            (
                "pose_probe",
                functools.partial(analyses.pose_probe, self),
                probe,
                (4 + 2) * self.scale.probe_steps * step_seconds("pose_probe") + 60,
                [f"train/{name}" for name in analyses.PROBED_RUNS],
            ),
            (
                "triangulation_predicted_pose",
                functools.partial(analyses.triangulation_predicted_pose, self),
                {"pose_of": analyses.PREDICTED_POSE},
                30,
                ["pose_probe"],
            ),
            (
                "flow_error",
                functools.partial(analyses.flow_error, self),
                {"pose_of": analyses.PREDICTED_POSE},
                60,
                [f"train/{analyses.MAIN_RUN}", "pose_probe"],
            ),
        ]
        if self.scale.further:
            waiting.append(
                (
                    "flow_finetuning",
                    functools.partial(analyses.flow_finetuning, self),
                    {"runs": list(paper_suite.FLOW_EXPERIMENT[1:])},
                    60,
                    ["flow_net", *(f"train/{n}" for n in paper_suite.FLOW_EXPERIMENT[1:])],
                )
            )

        def add_ready():
            for analysis in list(waiting):
                if all(need in identities for need in analysis[4]):
                    waiting.remove(analysis)
                    add(*analysis)

        names = list(self.runs)
        remaining = names.index(FIRST_REMAINING_RUN) if self.scale.further else len(names)
        add_runs([self.runs[name] for name in names[:remaining]], add_ready)
        if self.scale.further:  # the paper's remaining comparisons
            flow_config = paper_suite.flow_net_config(self.scale, height=0, width=0)
            add(
                "flow_net",
                functools.partial(analyses.flow_net, self),
                {**dataclasses.asdict(flow_config), "dis_timed_pairs": analyses.DIS_TIMED_PAIRS},
                self.scale.flow_net_steps * step_seconds("flow_net") + 60,
            )
            add_runs([self.runs[name] for name in names[remaining:]], add_ready)
        assert not waiting, f"analyses whose runs are not in the suite: {waiting}"
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
        """The results of every finished task made with the suite's present definition."""
        results = {}
        for task in self.tasks():
            result = read_result(self.results_dir, task.name)
            if result is not None and _same_identity(result, task):
                results[task.name] = result
        return results

    def run(self, only: Sequence[str] | None = None, *, commit: str = "") -> list[str]:
        """Runs every task not done yet (those named in `only`, if given; see
        `selected`). A task that fails is reported and the suite goes on.

        Training runs are collective (every process of a multi-process launch trains
        them); the classical baselines and analyses run in process 0, which alone
        writes results. Process 0 decides which tasks are pending.

        Returns:
          "<task>: <error>" for every task that failed.
        """
        import jax

        tasks = self.selected(only)
        by_name = {task.name: task for task in self.tasks()}
        done = [self._done(task) for task in tasks]
        if jax.process_count() > 1:
            from jax.experimental import multihost_utils

            done = [bool(d) for d in multihost_utils.broadcast_one_to_all(np.asarray(done))]
        pending = [task for task, finished in zip(tasks, done, strict=True) if not finished]
        for task, finished in zip(tasks, done, strict=True):
            if finished:
                self.print(f"{task.name}: done (reused {result_path(self.results_dir, task.name)})")
        estimates = {task.name: self._remaining_seconds(task) for task in pending}
        spent, estimated, failures = 0.0, 0.0, []
        for index, task in enumerate(pending):
            pace = spent / estimated if estimated > 600 else 1.0
            remaining = sum(estimates[t.name] for t in pending[index:])
            eta = _duration(remaining * pace)
            self.print(f"[{index + 1}/{len(pending)}] {task.name} — suite ETA {eta}")
            collective = task.name.startswith("train/")
            if not collective and jax.process_index() != 0:
                continue
            missing = [need for need in task.needs if not self._done(by_name[need])]
            if missing:
                self.print(f"{task.name}: skipped, needs {missing} first")
                continue
            # Its identity again, now that the tasks before it have finished (a run whose
            # rate a learning-rate check of this launch chose).
            task = {t.name: t for t in self.tasks()}[task.name]
            started = time.perf_counter()
            self._differences = []
            try:
                result = task.run()
            except Exception as error:  # noqa: BLE001 - one failed task must not stop the rest
                failures.append(f"{task.name}: {type(error).__name__}: {error}")
                self.print(f"{task.name}: FAILED ({failures[-1]}); going on with the others")
                continue
            seconds = time.perf_counter() - started
            result.update(task=task.name, identity=task.identity, seconds=seconds, commit=commit)
            if self._differences:
                result["retrained_differently"] = self._differences
            if jax.process_index() == 0:
                _write_json(result_path(self.results_dir, task.name), result)
            spent += seconds
            estimated += estimates[task.name]
        return failures

    def _done(self, task: Task) -> bool:
        result = read_result(self.results_dir, task.name)
        return result is not None and _same_identity(result, task)

    def _remaining_seconds(self, task: Task) -> float:
        """The task's estimated seconds, less the steps its run has checkpointed."""
        if task.name == "flow_net":
            left = self.scale.flow_net_steps - _checkpointed_step(self.flow_net_dir())
            return max(0, left) * step_seconds("flow_net") + 60
        if not task.name.startswith("train/"):
            return task.seconds
        run = self.runs[task.name.removeprefix("train/")]
        steps = paper_suite.run_steps(self.scale, run)
        left = max(0, steps - self._resumable_step(run))
        return left * step_seconds(run.model) + 30

    def _resumable_step(self, run: Run) -> int:
        """The newest checkpoint's step of the run's directory while it holds the run's
        present configuration (0 when it holds another, which training moves aside)."""

        run_dir = self.run_dir(run.name)
        step = _checkpointed_step(run_dir)
        if not step or self._rated(run) is None:
            return 0
        try:
            stored = workdir_lib.load_run_config(run_dir)
        except (FileNotFoundError, ValueError):
            return 0
        config = self._config(run, (stored.height, stored.width))
        return 0 if _other_configuration(run_dir, config) else step

    def _train(self, run: Run) -> dict[str, Any]:
        config = self._config(run)
        data = self.data(config.dataset)
        run_dir = self.run_dir(run.name)
        self.print(f"{run.name}: {config.steps} steps of {run.model} in {run_dir}")
        self._fit(run, config, data, evaluate=True)
        summary, abs_inv, parameters = self._score(run_dir, data)
        curves, train_seconds = _training_log(run_dir)
        return {
            "run": run.name,
            "model": run.model,
            "label": run.label,
            "dataset": data.name,
            "config": dataclasses.asdict(config),
            "parameters": parameters,
            "metrics": summary,
            "abs_inv_per_example": abs_inv,
            "curves": curves,
            "train_seconds": train_seconds,
        }

    def _fit(self, run: Run, config, data: Data, *, evaluate: bool) -> None:
        """Trains a run (resuming its checkpoints), after the flow network it starts from;
        `evaluate`: the test evaluations during training (the over-fitting curves)."""

        run_dir = self.run_dir(run.name)
        if run.model in paper_suite.FLOW_NET_MODELS:
            self._ensure_flow_net()
        self._supersede_other_configuration(run_dir, config)
        train.train_and_evaluate(
            config,
            run_dir,
            data.train,
            data.test if evaluate and config.eval_every else None,
            progress=self.progress,
            print_fn=self.print,
        )

    def _score(self, run_dir: Path, data: Data) -> tuple[dict[str, dict], np.ndarray, int]:
        """A finished run's test summary, per-example Abs-Inv and number of parameters."""

        model, variables, saved = workdir_lib.load_trained(run_dir)
        per_example, _ = evaluation.evaluate_source(
            model,
            variables,
            data.test,
            batch_size=saved.eval_batch_size,
            flow_source=saved.flow_source,
        )
        parameters = registry.parameter_counts(variables["params"])["total"]
        return (*analyses.scores(per_example), parameters)

    def trained(self, name: str):
        """(model, variables, config) of a finished run, for an analysis. A run whose
        result came without its checkpoint (results moved to another checkout) is
        retrained first, with the same configuration and seed, and scored against its
        result: the analyses must read the model the tables report."""

        run = self.runs[name]
        run_dir = self.run_dir(name)
        if self._resumable_step(run) < paper_suite.run_steps(self.scale, run):
            config = self._config(run)
            data = self.data(config.dataset)
            self.print(f"{name}: no checkpoint in {run_dir}; retraining it for the analyses")
            self._fit(run, config, data, evaluate=False)
            stored = read_result(self.results_dir, f"train/{name}")
            _, abs_inv, _ = self._score(run_dir, data)
            if stored is not None:
                self._note_reproduction(name, stored["abs_inv_per_example"], abs_inv)
        return workdir_lib.load_trained(run_dir)

    def _ensure_flow_net(self) -> None:
        """Retrains the flow network when its result came without its checkpoint (see
        `trained`); its test end-point error must be its result's."""

        run_dir = self.flow_net_dir()
        if _checkpointed_step(run_dir) >= self.scale.flow_net_steps:
            return
        self.print(f"flow_net: no checkpoint in {run_dir}; retraining it for the flow runs")
        *_, summary = self.fit_flow_net(evaluate=False)
        stored = read_result(self.results_dir, "flow_net")
        if stored is not None:
            network = flow_network.NETWORK
            self._note_reproduction(
                "flow_net", [stored["methods"][network]["epe"]], [summary[network]["epe"]]
            )

    def fit_flow_net(self, *, evaluate: bool):
        """Trains the flow network on the exact flow (resuming it); (model, variables, its
        step, its test end-point errors by method: the network's and the stored flow's).
        `evaluate`: the test evaluations during training (its curve)."""

        data = self.data(self.scale.dataset)
        config = paper_suite.flow_net_config(self.scale, height=data.height, width=data.width)
        run_dir = self.flow_net_dir()
        flow_training.train_flow(
            config,
            run_dir,
            data.train,
            data.test if evaluate else None,
            progress=self.progress,
            print_fn=self.print,
        )
        model, variables, _, step = trained_flow.load_flow_run(run_dir)
        _, _, summary = flow_network.evaluate_flow(
            model, variables, data.test, batch_size=config.eval_batch_size
        )
        return model, variables, step, summary

    def _note_reproduction(self, name: str, stored, retrained) -> None:
        difference = _reproduction(name, stored, retrained)
        self.print(f"{name}: retrained, " + (difference or "scores exactly its result"))
        if difference:
            self._differences.append(difference)

    def _supersede_other_configuration(self, run_dir: Path, config) -> None:
        """Moves a run directory trained with another configuration aside (never deleted),
        so that the run starts afresh instead of resuming another one's checkpoints."""
        changes = _other_configuration(run_dir, config)
        if not changes:
            return
        aside = run_dir.with_name(f"{run_dir.name}.superseded-{time.strftime('%Y%m%d-%H%M%S')}")
        self.print(f"{run_dir} was trained with other options {sorted(changes)}: moved to {aside}")
        run_dir.rename(aside)


def _reproduction(name: str, stored: Sequence[float], retrained: Sequence[float]) -> str | None:
    """None when a retrained run scores what its result says, else what differs (the
    same seed on another machine or library version need not give the same floats)."""
    stored, retrained = np.asarray(stored, np.float64), np.asarray(retrained, np.float64)
    if stored.shape == retrained.shape and np.allclose(stored, retrained, rtol=1e-4, atol=1e-7):
        return None
    return (
        f"{name} retrained scores {retrained.mean():.6g}, its result {stored.mean():.6g}: "
        "this analysis reads the retrained model (delete the run's result to redo the run "
        "and the tables with it)"
    )


def _matches(task: str, name: str) -> bool:
    """Whether `name` selects `task`: its whole name, or a leading group of it."""
    return task == name or task.startswith(name.rstrip("/") + "/")


def _duration(seconds: float) -> str:
    minutes = round(seconds / 60)
    return f"{minutes // 60} h {minutes % 60:02d} min" if minutes >= 60 else f"{minutes} min"
