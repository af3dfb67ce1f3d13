"""A suite's training runs in its workdir: each one's configuration at the rate its
learning-rate check chose, trained or resumed, scored on the test split, and retrained for
an analysis when its result came without its checkpoint.

    <workdir>/runs/<run>/        each training run's workdir (gld.runs.workdir)
    <workdir>/runs/flow_net/     the learned flow network's

A training run whose result is missing is trained once (`gld.training.scored_run`: it
resumes from its newest checkpoint, and a finished one is reused); a run directory
trained with another configuration is moved aside first, never deleted. The results
directory can travel without the runs (the launcher keeps it beside the report): an
analysis whose run has a result but no checkpoint here retrains that run with the same
configuration and seed, and checks whether it scores what its result says (the
analysis's result notes it if not). The analyses (`gld.paper.analyses`) read the runs
through `TrainingRuns`; `gld.paper.runner.SuiteRunner` is one, which also runs the
suite's tasks.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from gld.evaluation import flow_network
from gld.paper import analyses, rate_check, run_configs
from gld.paper import suite as paper_suite
from gld.paper.result_files import read_result
from gld.paper.scales import Scale
from gld.paper.suite import Run
from gld.runs import checkpoints as checkpoint_lib
from gld.runs import metrics_log, trained_flow
from gld.runs import workdir as workdir_lib
from gld.training import flow_trainer as flow_training
from gld.training import scored_run


@dataclasses.dataclass(frozen=True)
class Data:
    """A built dataset's splits, as the runner needs them."""

    name: str  # TFDS full name
    train: Any  # random-access record sources
    test: Any
    height: int
    width: int
    # decoded example -> the texture kind of each pixel of view 1 and the kinds' names
    # (`gld.analysis.regimes_run.TextureReader`); None where the dataset cannot tell.
    texture: Any = None


def _other_configuration(run_dir: Path, config) -> dict[str, Any]:
    """The options in which a run directory's training differs from `config` ({} when it
    holds none or the same)."""

    try:
        return workdir_lib.check_run_config(run_dir, config) or {}
    except ValueError as error:
        return {"architecture, dataset or resolution": str(error)}


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


class TrainingRuns:
    """A suite's training runs: their configurations, training, scores, and retraining.

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
        self.differences: list[str] = []  # retrained runs that score otherwise, in a task

    def data(self, dataset: str) -> Data:
        if dataset not in self._loaded:
            self._loaded[dataset] = self._data(dataset)
        return self._loaded[dataset]

    def version_of(self, dataset: str) -> dict[str, str]:
        """{"dataset_version": ...} of a dataset when the runner was told versions: a
        result of another version of the data is not this suite's (empty otherwise)."""
        if self._dataset_version is None:
            return {}
        return {"dataset_version": self._dataset_version(dataset)}

    def run_dir(self, name: str) -> Path:
        return self.workdir / "runs" / name

    def rated(self, run: Run) -> Run | None:
        """The run at the rate its model's learning-rate check chose
        (`gld.paper.suite.with_compared_rate`); None until that check has finished."""
        return paper_suite.with_compared_rate(
            self.scale, run, lambda n: read_result(self.results_dir, f"train/{n}")
        )

    def _config(self, run: Run, size: tuple[int, int] | None = None):
        """The run's configuration at `size` (height, width); by default its dataset's."""
        rated = self.rated(run)
        if rated is None:
            raise RuntimeError(
                f"{run.name}: the learning-rate check of {run.rate_of} has not finished"
            )
        run = rated
        if size is None:
            data = self.data(self.scale.varying_dataset if run.varying else self.scale.dataset)
            size = (data.height, data.width)
        return run_configs.run_config(
            self.scale,
            run,
            height=size[0],
            width=size[1],
            flow_net_workdir=str(self.flow_net_dir()),
        )

    def compared_run(self, name: str) -> str:
        """The run of a main-table model that its comparisons use
        (`gld.paper.rate_check.compared_run`); both of its runs have finished."""
        run = rate_check.compared_run(
            self.scale, name, lambda n: read_result(self.results_dir, f"train/{n}")
        )
        if run is None:
            raise RuntimeError(f"{name}: its learning-rate check has not finished")
        return run

    def flow_net_dir(self) -> Path:
        return self.workdir / "runs" / "flow_net"

    def resumable_step(self, run: Run) -> int:
        """The newest checkpoint's step of the run's directory while it holds the run's
        present configuration (0 when it holds another, which training moves aside)."""

        run_dir = self.run_dir(run.name)
        step = checkpoint_lib.last_checkpointed_step(run_dir)
        if not step or self.rated(run) is None:
            return 0
        try:
            stored = workdir_lib.load_run_config(run_dir)
        except (FileNotFoundError, ValueError):
            return 0
        config = self._config(run, (stored.height, stored.width))
        return 0 if _other_configuration(run_dir, config) else step

    def train_and_score(self, run: Run) -> dict[str, Any]:
        """Trains a run (resuming it; a finished one is reused) and scores it on the test
        split: its result."""
        config = self._config(run)
        data = self.data(config.dataset)
        run_dir = self.run_dir(run.name)
        self._fit(run, config, data, evaluate=True)
        scored = scored_run.score(run_dir, data.test)
        summary, abs_inv = analyses.scores(scored.per_example)
        curves, train_seconds = _training_log(run_dir)
        return {
            "run": run.name,
            "model": run.model,
            "label": run.label,
            "dataset": data.name,
            "config": dataclasses.asdict(config),
            "parameters": scored.parameters,
            "metrics": summary,
            "abs_inv_per_example": abs_inv,
            "curves": curves,
            "train_seconds": train_seconds,
        }

    def _fit(self, run: Run, config, data: Data, *, evaluate: bool) -> None:
        """Trains a run unless it has finished (resuming its checkpoints), after the flow
        network it starts from; `evaluate`: the test evaluations during training (the
        over-fitting curves)."""

        run_dir = self.run_dir(run.name)
        if run.model in paper_suite.FLOW_NET_MODELS:
            self._ensure_flow_net()
        self._supersede_other_configuration(run_dir, config)
        scored_run.train_unless_finished(
            run.name,
            config,
            run_dir,
            data.train,
            data.test if evaluate and config.eval_every else None,
            progress=self.progress,
            print_fn=self.print,
        )

    def trained(self, name: str):
        """(model, variables, config) of a finished run, for an analysis. A run whose
        result came without its checkpoint (results moved to another checkout) is
        retrained first, with the same configuration and seed, and scored against its
        result: the analyses must read the model the tables report."""

        run = self.runs[name]
        run_dir = self.run_dir(name)
        if self.resumable_step(run) < run_configs.run_steps(self.scale, run):
            config = self._config(run)
            data = self.data(config.dataset)
            self.print(f"{name}: no checkpoint in {run_dir}; retraining it for the analyses")
            self._fit(run, config, data, evaluate=False)
            stored = read_result(self.results_dir, f"train/{name}")
            _, abs_inv = analyses.scores(scored_run.score(run_dir, data.test).per_example)
            if stored is not None:
                self._note_reproduction(name, stored["abs_inv_per_example"], abs_inv)
        return workdir_lib.load_trained(run_dir)

    def _ensure_flow_net(self) -> None:
        """Retrains the flow network when its result came without its checkpoint (see
        `trained`); its test end-point error must be its result's."""

        run_dir = self.flow_net_dir()
        if checkpoint_lib.last_checkpointed_step(run_dir) >= self.scale.flow_net_steps:
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
        config = run_configs.flow_net_config(self.scale, height=data.height, width=data.width)
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
            self.differences.append(difference)

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
