"""The results a suite's report reads (`ReportResults`), and the targets its sections check.

What the report's sections share: each run's result by name, what stands for a result
the report does not have (not run yet, or made by uncommitted code and refused), the
classical references, the rows' labels, the depth table every section writes, the run
each comparison uses, and the verdicts of the targets in the report's order.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

from gld.paper import analyses as paper_analyses
from gld.paper import rate_check, run_configs, scales
from gld.paper import suite as paper_suite
from gld.paper.report_cells import (
    NOT_RUN,
    PaperRef,
    metric,
    metric_cells,
    paper_cell,
    paper_header,
    paper_x_mean_cell,
    table_row,
    verdict,
)
from gld.paper.scales import Scale

CLASSICAL_LABELS = {
    "dataset_mean": "dataset mean",
    "oracle_pair_median": "per-pair oracle constant (sees the truth)",
    "triangulation_gt_pose": "triangulation, true pose",
    "sfm_flow": "essential-matrix SfM on the flow",
    "triangulation_predicted_pose": "triangulation, pose of the Pretrained-Full probe on "
    "the main run's encoder",
}
# The commit stamp of a result made with tracked files changed from their commit
# (`experiments.common.commit_stamp`).
UNCOMMITTED = "+changes"
RERUN = "needs a re-run at a clean commit"
# The targets, by the keys of the hand-written discussion beside the report.
TARGETS = ("main", "ablations", "density", "varying", "pose_probe", "flow_net", "finetuning")


def uncommitted(results: dict[str, dict]) -> dict[str, str]:
    """Task -> commit stamp of each result made by uncommitted code (its stamp ends with
    "+changes"): it needs a re-run at a clean commit."""
    return {
        task: result["commit"]
        for task, result in sorted(results.items())
        if (result.get("commit") or "").endswith(UNCOMMITTED)
    }


class ReportResults:
    """A suite's results as its report reads them, and the verdicts of its targets.

    A report made at a clean commit (or at an unknown one) refuses the results made by
    uncommitted code (`uncommitted`): it leaves them out, and their cells say they need a
    re-run at a clean commit. A report made by uncommitted code itself (its `commit` ends
    with "+changes": one made while the code is being changed, whose results are made
    so too) reports them, and lists them as needing that re-run.

    Args:
      scale: the suite.
      results: task name -> result (`gld.paper.runner.SuiteRunner.finished`).
      results_dir: where the results are (for their arrays and figures).
      commit: the commit stamp the report is made at (`experiments.common.commit_stamp`).
    """

    def __init__(
        self, scale: Scale, results: dict[str, dict], results_dir: str | Path, commit: str = ""
    ):
        self.scale = scale
        self.uncommitted = uncommitted(results)
        # The results left out: all those made by uncommitted code, unless this report is.
        self.refused = {} if commit.endswith(UNCOMMITTED) else self.uncommitted
        self.results = {task: r for task, r in results.items() if task not in self.refused}
        self.results_dir = Path(results_dir)
        self.runs = {run.name: run for run in paper_suite.suite_runs(scale)}
        # The main table's models of this suite that the learning-rate check trains twice.
        self.checked = [n for n in rate_check.RATE_CHECKED if n in self.runs]
        # (key, name, holds, numbers) of each target, in the report's order.
        self.targets: list[tuple[str, str, bool | None, str]] = []

    def run(self, name: str) -> dict | None:
        return self.results.get(f"train/{name}")

    def missing(self, task: str) -> str:
        """What stands for a task's result that the report does not have: not run yet,
        or made by uncommitted code and not reported."""
        return RERUN if task in self.refused else NOT_RUN

    def missing_run(self, name: str) -> str:
        return self.missing(f"train/{name}")

    def missing_row(self, name: str, varying: bool = False) -> str:
        """`missing` of a table's row: a run, a classical method or an analysis."""
        if name in self.runs:
            return self.missing_run(name)
        if name in paper_analyses.CLASSICAL:
            dataset = self.scale.varying_dataset if varying else self.scale.dataset
            return self.missing(f"classical/{dataset.split('/')[-1]}")
        return self.missing(name)

    def classical(self, name: str, varying: bool = False) -> dict | None:
        dataset = self.scale.varying_dataset if varying else self.scale.dataset
        result = self.results.get(f"classical/{dataset.split('/')[-1]}")
        return None if result is None else result["methods"].get(name)

    def mean_reference(self, varying: bool = False) -> float | None:
        return metric(self.classical("dataset_mean", varying))

    def oracle_reference(self, varying: bool = False) -> float | None:
        return metric(self.classical("oracle_pair_median", varying))

    def label(self, name: str) -> str:
        if name not in self.runs:
            return CLASSICAL_LABELS.get(name, name)
        run = self.runs[name]
        label = run.label
        if run.model in scales.LARGE_MODELS:
            label += f" ({run_configs.run_steps(self.scale, run):,} steps)"
        result = self.run(name)
        if result is not None and (collapsed := rate_check.collapse(result)) is not None:
            label += f" — collapsed: vanishing gradient from step {collapsed[0]:,}"
        return label

    def compared_run(self, name: str) -> str | None:
        """The run of a main-table model that its comparisons use
        (`gld.paper.rate_check.compared_run`)."""
        return rate_check.compared_run(self.scale, name, self.run)

    def table(
        self,
        rows: Sequence[tuple[str, dict | None, PaperRef]],
        table: str,
        varying: bool = False,
    ) -> str:
        """Our rows with the paper's numbers beside them, from `table` of
        `gld.paper.numbers` unless a row's cell names another."""
        reference = self.mean_reference(varying)
        text = f"| method | Abs-Inv | Abs-Rel | S-RMSE | x mean | {paper_header(table)} |\n"
        text += "|---|---|---|---|---|---|---|\n"
        for name, result, ref in rows:
            text += table_row(
                [
                    self.label(name),
                    *metric_cells(result, reference, self.missing_row(name, varying)),
                    paper_cell(ref, table),
                    paper_x_mean_cell(ref),
                ]
            )
        return text

    def target(self, key: str, name: str, holds: bool | None, detail: str) -> str:
        """A target's verdict; `key` names it in the hand-written discussion."""
        assert key in TARGETS, key
        self.targets.append((key, name, holds, detail))
        return f"Target — {name}: {verdict(holds)}. {detail}\n\n"

    def rate(self, name: str) -> str:
        return f"{self.run(name)['config']['learning_rate']:g}"
