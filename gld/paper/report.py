"""The report of a suite (`gld.paper.runner`): every table of the paper's experimental
section with our numbers beside the paper's, the orderings it claims checked, and the
figures as PNG.

    <report_dir>/README.md     the tables, targets, budgets, protocol, commit
    <report_dir>/*.png         density, flow errors, over-fitting, qualitative grid, filters

The paper's numbers all come from `gld.paper.numbers` (its Scenes11 column, by table of
the paper), and each column of them names its table: the paper gives its own model
different numbers in different tables. A run or analysis not finished yet appears as
"not run yet". A result made by uncommitted code (its commit stamp ends with "+changes")
is listed as needing a re-run at a clean commit, and a report made at a clean commit does
not report it (`Report`).

The hand-written discussion beside the report (`discussion.md`) writes the suite's
numbers as placeholders that the report fills in from the results (`Report.fill`), and
marks any other number it quotes; a number written by hand is an error.
"""

from __future__ import annotations

import re
import shutil
import textwrap
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from gld import files as files_lib
from gld.analysis import flow_error
from gld.evaluation import flow_network, metrics, reports
from gld.paper import analyses as paper_analyses
from gld.paper import numbers as paper
from gld.paper import runner as paper_runner
from gld.paper import suite as paper_suite
from gld.paper.suite import Scale

SUPERVISED_BASELINES = ("small_encdec_1px", "eigen_1px", "dispnet_1px", "fcrn_1px")
ABLATION_ROWS = (
    "global_local_1px",
    "global_local_image_pair",
    "global_local_no_coordconv",
    "global_local_no_global_module",
    "global_local_no_flow",
)
SELF_SUPERVISED = ("struct2depth", "struct2depth_flow")
POSE_LABELS = {
    "scratch_mlp": "Scratch-MLP (random encoder, MLP trained)",
    "pretrained_mlp": "Pretrained-MLP (the trained model's encoder, MLP trained)",
    "scratch_full": "Scratch-Full (random encoder, all trained)",
    "pretrained_full": "Pretrained-Full (the trained model's encoder, all trained)",
    "mean_pose": "the test pairs' mean pose (a reference that sees the truth)",
}
CLASSICAL_LABELS = {
    "dataset_mean": "dataset mean",
    "oracle_pair_median": "per-pair oracle constant (sees the truth)",
    "triangulation_gt_pose": "triangulation, true pose",
    "sfm_flow": "essential-matrix SfM on the flow",
    "triangulation_predicted_pose": "triangulation, pose of the Pretrained-Full probe on "
    "the main run's encoder",
}
METRICS = ("abs_inv", "abs_rel", "s_rmse")
NOT_RUN = "not run yet"
# The commit stamp of a result made with tracked files changed from their commit
# (`experiments.common.commit_stamp`).
UNCOMMITTED = "+changes"
RERUN = "needs a re-run at a clean commit"
# The targets, by the keys of the hand-written discussion beside the report.
TARGETS = ("main", "ablations", "density", "varying", "pose_probe", "flow_net", "finetuning")
DISCUSSION = "discussion.md"
# The main target: global-local this far below every learned baseline (a margin a little
# below the smallest of the paper's, which the target's name gives beside it).
MAIN_MARGIN = 0.15
# A placeholder of the discussion: {kind:argument[:argument...]} (`Report.fill`).
PLACEHOLDER = re.compile(r"\{(\w+):([^{}]*)\}")
# A number the discussion may not write by hand: one with a decimal point or a percent.
HAND_WRITTEN_NUMBER = re.compile(r"\d+(?:\.\d+)? ?%|\d+\.\d+")
# The placeholders' kinds and their arguments. <name>: a run of the suite, a main-table
# model's compared run (compared/<run>), a classical method (varying/<method> on the
# varying split) or triangulation_predicted_pose; numbers per test pair compare two names
# of the same split.
PLACEHOLDERS = {
    "abs_inv": "abs_inv:<name>",  # 0.0282
    "x_mean": "x_mean:<name>",  # 0.83x: Abs-Inv as a multiple of its split's dataset mean
    "change": "change:<name>:<reference>",  # +14.7%: Abs-Inv against the reference's
    "below": "below:<name>:<reference>",  # 13%: how far Abs-Inv is below the reference's
    "loss": "loss:<run>",  # 0.0298: training loss, last quarter (`training_loss`)
    "test_at": "test_at:<run>:<step>",  # 0.0330: test Abs-Inv during training
    "worse_pairs": "worse_pairs:<name>:<reference>",  # 68%: pairs with a higher Abs-Inv
    "better_pairs": "better_pairs:<name>:<reference>",  # 62%: pairs with a lower Abs-Inv
    "paired_t": "paired_t:<name>:<reference>",  # +6.3: mean difference / its std error
    "rotation": "rotation:<run>:<setting>",  # 3.36: the pose probe's error, degrees
    "translation": "translation:<run>:<setting>",  # 65.3
    "paper": "paper:<table>:<row>[:<column>]",  # 0.031 / 0.43 / 0.61, or 0.031
    "paper_change": "paper_change:<table>:<row>:<reference>",  # +24%
    "paper_below": "paper_below:<table>:<row>:<reference>",  # 47%
    "paper_x_mean": "paper_x_mean:<table>:<row>",  # 0.45x
    "quote": "quote:<text>",  # a number from elsewhere, as written
}


def _metric(result: dict | None, name: str = "abs_inv") -> float | None:
    if result is None:
        return None
    return result["metrics"][name]["mean"]


def _cells(result: dict | None, reference: float | None, missing: str = NOT_RUN) -> list[str]:
    if result is None:
        return [missing, "", "", ""]
    summary = result["metrics"]
    cells = [f"{summary['abs_inv']['mean']:.4f} ± {summary['abs_inv']['std']:.4f}"]
    cells += [f"{summary[name]['mean']:.3f}" for name in METRICS[1:]]
    cells.append(f"{summary['abs_inv']['mean'] / reference:.2f}" if reference else "")
    return cells


# Where a row of ours has the paper's numbers beside it: (table of `gld.paper.numbers`,
# the key of its row), or None.
PaperRef = tuple[str, str] | None


def _paper(ref: PaperRef, table: str | None = None, columns: int | None = None) -> str:
    """The paper's numbers of a row as it prints them (Abs-Inv / Abs-Rel / S-RMSE in the
    depth tables; its first `columns` only, if given); the paper's table is named when it
    is not `table`, the one the column's header names. "—" without them."""
    numbers = None if ref is None else paper.printed(*ref)
    if numbers is None:
        return "—"
    text = " / ".join(numbers[:columns])
    return text if ref[0] == table else f"{text} (`{paper.TABLES[ref[0]].label}`)"


def _paper_x_mean(ref: PaperRef) -> str:
    """The paper's Abs-Inv of a row as a multiple of the paper's dataset mean's."""
    multiple = None if ref is None else paper.x_mean(*ref)
    return "—" if multiple is None else f"{multiple:.2f}"


def _paper_header(table: str) -> str:
    return f"paper (Scenes11, `{paper.TABLES[table].label}`) | paper x mean"


def _percent_range(values: Sequence[float]) -> str:
    """18-33%: the range of fractions, in whole percent."""
    low, high = (round(100 * v) for v in (min(values), max(values)))
    return f"{low}%" if low == high else f"{low}-{high}%"


def _multiple_range(values: Sequence[float]) -> str:
    """0.45-0.67x: the range of multiples."""
    low, high = f"{min(values):.2f}", f"{max(values):.2f}"
    return f"{low}x" if low == high else f"{low}-{high}x"


def _row(cells: Sequence[Any]) -> str:
    return "| " + " | ".join(str(c) for c in cells) + " |\n"


def _verdict(holds: bool | None) -> str:
    return {True: "**holds**", False: "**does not hold**", None: "not measured yet"}[holds]


def uncommitted(results: dict[str, dict]) -> dict[str, str]:
    """Task -> commit stamp of each result made by uncommitted code (its stamp ends with
    "+changes"): it needs a re-run at a clean commit."""
    return {
        task: result["commit"]
        for task, result in sorted(results.items())
        if (result.get("commit") or "").endswith(UNCOMMITTED)
    }


class Report:
    """Collects the sections of a suite's report from its results.

    A report made at a clean commit (or at an unknown one) refuses the results made by
    uncommitted code (`uncommitted`): it leaves them out, and their cells say they need a
    re-run at a clean commit. A report made by uncommitted code itself (its `commit` ends
    with "+changes": one made while the code is being changed, whose results are made
    so too) reports them, and lists them as needing that re-run.

    Args:
      scale: the suite.
      results: task name -> result (`SuiteRunner.run`).
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
        self.checked = [n for n in paper_suite.RATE_CHECKED if n in self.runs]
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

    def _missing_row(self, name: str, varying: bool = False) -> str:
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
        return _metric(self.classical("dataset_mean", varying))

    def oracle_reference(self, varying: bool = False) -> float | None:
        return _metric(self.classical("oracle_pair_median", varying))

    def _label(self, name: str) -> str:
        if name not in self.runs:
            return CLASSICAL_LABELS.get(name, name)
        run = self.runs[name]
        label = run.label
        if run.model in paper_suite.LARGE_MODELS:
            label += f" ({paper_suite.run_steps(self.scale, run):,} steps)"
        result = self.run(name)
        if result is not None and (collapsed := paper_suite.collapse(result)) is not None:
            label += f" — collapsed: vanishing gradient from step {collapsed[0]:,}"
        return label

    def compared_run(self, name: str) -> str | None:
        """The run of a main-table model that its comparisons use
        (`gld.paper.suite.compared_run`)."""
        return paper_suite.compared_run(self.scale, name, self.run)

    def _table(
        self,
        rows: Sequence[tuple[str, dict | None, PaperRef]],
        table: str,
        varying: bool = False,
    ) -> str:
        """Our rows with the paper's numbers beside them, from `table` of
        `gld.paper.numbers` unless a row's cell names another."""
        reference = self.mean_reference(varying)
        text = f"| method | Abs-Inv | Abs-Rel | S-RMSE | x mean | {_paper_header(table)} |\n"
        text += "|---|---|---|---|---|---|---|\n"
        for name, result, ref in rows:
            text += _row(
                [
                    self._label(name),
                    *_cells(result, reference, self._missing_row(name, varying)),
                    _paper(ref, table),
                    _paper_x_mean(ref),
                ]
            )
        return text

    def _target(self, key: str, name: str, holds: bool | None, detail: str) -> str:
        """A target's verdict; `key` names it in the hand-written discussion."""
        assert key in TARGETS, key
        self.targets.append((key, name, holds, detail))
        return f"Target — {name}: {_verdict(holds)}. {detail}\n\n"

    # -- the hand-written discussion's placeholders ------------------------------------

    def fill_discussion(
        self, discussion: dict[str, str], path: Path | str = DISCUSSION
    ) -> dict[str, str]:
        """The discussion's sections with their placeholders filled in (`fill`).

        ValueError naming every number written by hand in them (one with a decimal point
        or a percent, outside a placeholder: it would not follow the results when they
        change) and every placeholder the report cannot fill."""
        problems, filled = [], {}
        for key, text in discussion.items():
            bare = PLACEHOLDER.sub(" ", text)
            problems += [
                f"{number.group()!r} written by hand (## {key})"
                for number in HAND_WRITTEN_NUMBER.finditer(bare)
            ]
            try:
                # One line a paragraph: a filled-in line could start like a list item.
                filled[key] = re.sub(r"(?<!\n)\n(?!\n)", " ", self.fill(text))
            except ValueError as error:
                problems.append(f"{error} (## {key})")
        if problems:
            raise ValueError(
                f"{path}: " + "; ".join(problems) + ". Write the suite's numbers as "
                "placeholders ({" + "}, {".join(PLACEHOLDERS.values()) + "}) and quote any "
                "other number as {quote:...}"
            )
        return filled

    def fill(self, text: str) -> str:
        """`text` with each placeholder replaced by the number it names, formatted as the
        report prints it (the kinds: `PLACEHOLDERS`). A run without a result gives
        "(not run yet)" or "(needs a re-run at a clean commit)"; an unknown kind, run or
        row is a ValueError."""
        return PLACEHOLDER.sub(lambda match: self._placeholder(*match.groups()), text)

    def _placeholder(self, kind: str, argument: str) -> str:
        if kind == "quote":  # a number from elsewhere: the paper's text, a run by hand
            return argument
        if kind not in PLACEHOLDERS:
            raise ValueError(f"unknown placeholder {{{kind}:{argument}}}")
        args = argument.split(":")
        if len(args) != PLACEHOLDERS[kind].count(":") and not kind.startswith("paper"):
            raise ValueError(f"{{{kind}:{argument}}}: not {{{PLACEHOLDERS[kind]}}}")
        if kind.startswith("paper"):
            return _paper_placeholder(kind, args)
        if kind in ("rotation", "translation"):
            result = self.results.get("pose_probe")
            if result is None:
                return f"({self.missing('pose_probe')})"
            error = result["errors"].get(args[0], {}).get(args[1])
            if error is None:
                raise ValueError(f"{{{kind}:{argument}}}: the pose probe has no such setting")
            if kind == "rotation":
                return f"{error['rotation_deg']:.2f}"
            return f"{error['translation_deg']:.1f}"
        names = args[:1] if kind in ("abs_inv", "x_mean", "loss", "test_at") else args
        named = [self._named(name, kind, argument) for name in names]
        if kind in ("loss", "test_at") and not named[0][1].startswith("train/"):
            raise ValueError(f"{{{kind}:{argument}}}: {args[0]!r} is no training run")
        for result, task, _ in named:
            if result is None:
                return f"({self.missing(task)})"
        (first, _, varying), *rest = named
        value = first["metrics"]["abs_inv"]["mean"]
        if kind == "abs_inv":
            return f"{value:.4f}"
        if kind == "x_mean":
            mean = self.mean_reference(varying)
            return f"({NOT_RUN})" if mean is None else f"{value / mean:.2f}x"
        if kind == "loss":
            loss = paper_suite.training_loss(first)
            return "—" if loss is None else f"{loss:.4f}"
        if kind == "test_at":
            steps = {int(step): test for step, test in first["curves"]["test"]}
            if int(args[1]) not in steps:
                raise ValueError(f"{{{kind}:{argument}}}: no test evaluation at that step")
            return f"{steps[int(args[1])]:.4f}"
        (second, _, other_varying) = rest[0]
        reference = second["metrics"]["abs_inv"]["mean"]
        if kind == "change":
            return f"{value / reference - 1:+.1%}"
        if kind == "below":
            return f"{1 - value / reference:.0%}"
        # Per test pair: the two runs' arrays are in the order of their split.
        if varying != other_varying:
            raise ValueError(f"{{{kind}:{argument}}}: the pairs of two splits are not joined")
        difference = np.asarray(first["abs_inv_per_example"]) - np.asarray(
            second["abs_inv_per_example"]
        )
        if kind == "worse_pairs":
            return f"{np.mean(difference > 0):.0%}"
        if kind == "better_pairs":
            return f"{np.mean(difference < 0):.0%}"
        error = difference.std(ddof=1) / np.sqrt(difference.size)
        return f"{difference.mean() / error:+.1f}"  # paired_t

    def _named(self, name: str, kind: str, argument: str) -> tuple[dict | None, str, bool]:
        """(result, its task, on the varying split) of a name in a placeholder: a run, a
        main-table model's compared run (`compared/<run>`), a classical method
        (`varying/<method>` on the varying split) or the triangulation with the probe's
        pose."""
        if name.startswith("compared/") and name.removeprefix("compared/") in self.checked:
            run = self.compared_run(name.removeprefix("compared/"))
            if run is None:  # its learning-rate check has not finished
                return None, f"train/{name.removeprefix('compared/')}", False
            return self._named(run, kind, argument)
        if name in self.runs:
            return self.run(name), f"train/{name}", self.runs[name].varying
        varying = name.startswith("varying/")
        method = name.removeprefix("varying/")
        if method in paper_analyses.CLASSICAL:
            dataset = self.scale.varying_dataset if varying else self.scale.dataset
            return self.classical(method, varying), f"classical/{dataset.split('/')[-1]}", varying
        if name == "triangulation_predicted_pose":
            return self.results.get(name), name, False
        raise ValueError(f"{{{kind}:{argument}}}: {name!r} is no run or method of the suite")

    # -- sections ---------------------------------------------------------------------

    def main_table(self) -> str:
        """The main table: each main-table model at the suite's rate, then at the rate of
        the learning-rate check, then the classical references. The paper's numbers sit
        on the row of the run each comparison uses (the rate the check chose; the suite's
        rate while the check is unfinished), so the other rate's row, which nothing
        compares, has none; the dataset mean's row has the paper's dataset mean."""
        table = "results_sparse"
        compared = {n: self.compared_run(n) or n for n in self.checked}
        rows = [(n, self.run(n), (table, n) if compared[n] == n else None) for n in self.checked]
        if self.scale.check_learning_rate is not None:
            for name in self.checked:
                low = paper_suite.low_rate_name(name)
                rows.append((low, self.run(low), (table, name) if compared[name] == low else None))
        rows += [
            (n, self.classical(n), paper.MEAN if n == paper.MEAN[1] else None)
            for n in paper_analyses.CLASSICAL
        ]
        text = "## 1. Main table: one supervised pixel per image\n\n" + self._table(rows, table)
        text += "\n" + self._paper_mean_note(table, compared) + "\n\n"
        if any(n in self.runs for n in SELF_SUPERVISED):
            text += (
                "The self-supervised baseline (Struct2Depth / monodepth2 family, "
                "`gld.models.baselines.self_supervised`) learns depth and pose from the image pair "
                "alone with a photometric reprojection loss (SSIM + L1, per-pixel minimum, "
                "auto-masking, edge-aware smoothness); no depth label. Its depth is scored in "
                "units of its pose network's translation (||t|| = 1, the paper's "
                "normalisation). Struct2Depth's object-motion model is left out: the scenes "
                "are static.\n\n"
            )
        text += self.rate_check()
        compared = {n: self.compared_run(n) for n in self.checked}
        ours = _metric(self.run(compared.get("global_local_1px") or ""))
        gaps, short = {}, {}
        for name in SUPERVISED_BASELINES:
            theirs = _metric(self.run(compared.get(name, name) or ""))
            if ours is None or theirs is None:
                continue
            limited = self.scale.large_steps < self.scale.steps and (
                self.runs[name].model in paper_suite.LARGE_MODELS
            )
            (short if limited else gaps)[self.runs[name].label] = 1 - ours / theirs
        expected = 2 if self.scale.large_steps < self.scale.steps else 4
        holds = None if len(gaps) < expected else all(g >= MAIN_MARGIN for g in gaps.values())
        detail = "global-local's Abs-Inv below each baseline's: " + (
            ", ".join(f"{name} {gap:.0%}" for name, gap in gaps.items()) or "—"
        )
        if self.scale.check_learning_rate is not None and ours is not None:
            detail += (
                " (each at the rate of the learning-rate check: "
                + ", ".join(
                    f"{self.runs[n].label} {self._rate(r)}" for n, r in compared.items() if r
                )
                + ")"
            )
        if short:
            detail += "; at their shorter budget (not counted in the verdict): " + ", ".join(
                f"{name} {gap:.0%}" for name, gap in short.items()
            )
        unsupervised = {
            self.runs[n].label: 1 - ours / theirs
            for n in SELF_SUPERVISED
            if ours is not None
            and (run := compared.get(n)) is not None
            and (theirs := _metric(self.run(run))) is not None
        }
        if unsupervised:
            detail += "; the self-supervised baselines (no depth labels; not counted): " + (
                ", ".join(f"{name} {gap:.0%}" for name, gap in unsupervised.items())
            )
        # The paper's margins over the same baselines, from its main table.
        model = paper.TABLES[table].model
        margins = [
            1 - paper.value(table, model) / paper.value(table, name)
            for name in SUPERVISED_BASELINES
        ]
        text += self._target(
            "main",
            f"global-local at least {MAIN_MARGIN:.0%} below every learned baseline with the "
            f"same budget (the paper's Scenes11: {_percent_range(margins)})",
            holds,
            detail + ".",
        )
        return text

    def _paper_mean_note(self, table: str, compared: dict[str, str]) -> str:
        """Where the main table's paper numbers come from, and the paper's models and ours
        as multiples of their dataset means."""
        mean_table = paper.MEAN[0]
        model = paper.TABLES[table].model
        text = (
            f"The paper's numbers: its Scenes11 column of `{paper.TABLES[table].label}`, "
            "beside the run each comparison uses"
            + (
                " (the rate the learning-rate check chose; the other rate's row has none)"
                if self.scale.check_learning_rate is not None
                else ""
            )
            + f". The paper's dataset mean ({paper.value(*paper.MEAN):.3f}) is from "
            f"`{paper.TABLES[mean_table].label}`, the only table of the paper that gives it"
        )
        if (ours := paper.value(mean_table, model)) != (theirs := paper.value(table, model)):
            text += (
                f", where the paper's model scores {ours:.3f} "
                f"({paper.x_mean(mean_table, model):.2f}x), not this table's {theirs:.3f} "
                f"({paper.x_mean(table, model):.2f}x)"
            )
        labelled = [model, *SUPERVISED_BASELINES]
        theirs = [paper.x_mean(table, n) for n in labelled if n in self.runs]
        text += (
            ". \"paper x mean\" is the paper's Abs-Inv as a multiple of it: the paper's "
            f"models trained with depth labels score {_multiple_range(theirs)} it"
        )
        reference = self.mean_reference()
        here = [_metric(self.run(compared.get(n, n))) for n in labelled if n in self.runs]
        if reference and here and None not in here:
            multiples = [value / reference for value in here]
            text += f"; here the same models, at their compared rate, {_multiple_range(multiples)}"
        return text + "."

    def _rate(self, name: str) -> str:
        return f"{self.run(name)['config']['learning_rate']:g}"

    def rate_check(self) -> str:
        """The main table's models at the suite's rate and at the check's, the training
        loss that picks the compared one, and which runs collapsed."""
        if self.scale.check_learning_rate is None:
            return ""
        rates = (self.scale.learning_rate, self.scale.check_learning_rate)
        text = "### Learning-rate check\n\n| model | " + " | ".join(
            f"peak rate {rate:g}: test Abs-Inv / training loss" for rate in rates
        )
        text += " | compared at |\n|---|---|---|---|\n"
        for name in self.checked:
            cells = []
            for run_name in (name, paper_suite.low_rate_name(name)):
                result = self.run(run_name)
                if result is None:
                    cells.append(self.missing_run(run_name))
                    continue
                loss = paper_suite.training_loss(result)
                cell = f"{_metric(result):.4f} / " + ("—" if loss is None else f"{loss:.4f}")
                if paper_suite.collapse(result) is not None:
                    cell += " (collapsed)"
                cells.append(cell)
            compared = self.compared_run(name)
            text += _row([self.runs[name].label, *cells, self._rate(compared) if compared else ""])
        return text + (
            "\nOne shared rate can suit one model and starve another, so the main table's "
            "learned models are trained at two peak rates, and every comparison (the target "
            "below, the over-fitting figure, the qualitative grid) takes each at the rate "
            "with the lower training loss (the L1 "
            "inverse-depth loss on its supervised pixels over the last quarter of training, "
            "never the test split), unless that run collapsed and the other did not. A run "
            f'"collapsed" when its gradient norm is below {paper_suite.VANISHED_GRADIENT:g} of '
            "its largest logged one at "
            "a quarter or more of its logged steps: its output saturated and it stopped "
            "learning. A model's runs at the other densities and on the varying intrinsics "
            "train at its compared rate too; the ablations, at the suite's rate.\n\n"
        )

    def learned_flow(self, figure_dir: Path) -> str:
        """The learned flow network against DIS: end-point error and speed ("" in a suite
        without the further runs)."""
        if not self.scale.further:
            return ""
        text = "## 10. Learned optical flow\n\n"
        result = self.results.get("flow_net")
        holds, detail = None, "—"
        if result is None:
            text += self.missing("flow_net") + ".\n\n"
        else:
            text += (
                "| method | EPE (px) | ± std | median | > 3 px | parameters | ms/pair |\n"
                "|---|---|---|---|---|---|---|\n"
            )
            rows = (
                (flow_network.NETWORK, "flow network (PWC-Net style, learned)", result),
                (flow_network.STORED_FLOW, "DIS (OpenCV, the stored flow)", None),
            )
            for key, label, own in rows:
                row = result["methods"][key]
                milliseconds = result["network_ms"] if own else result.get("dis_ms")
                text += _row(
                    [
                        label,
                        f"{row['epe']:.3f}",
                        f"{row['epe_std']:.3f}",
                        f"{row['epe_median']:.3f}",
                        f"{100 * row['outliers']:.1f}%",
                        f"{result['parameters']:,}" if own else "—",
                        "—" if milliseconds is None else f"{milliseconds:.1f}",
                    ]
                )
            recipe = paper_suite.flow_net_config(self.scale, height=0, width=0)
            curve = ", ".join(f"{v:.3f}" for _, v in result["curve"])
            text += (
                f"\nEnd-point error against the exact flow over the valid pixels of the "
                f"{result['methods'][flow_network.NETWORK]['count']} test pairs, mean over "
                f"pairs; the network trained {recipe.steps:,} steps at batch "
                f"{recipe.batch_size} on the training pairs' exact flow (Adam "
                f"{recipe.learning_rate:g}, {recipe.lr_schedule}; `gld.training.flow_trainer`), "
                "test "
                f"EPE over training: {curve or '—'}. ms/pair: the network's median forward "
                "pass at batch 1 (compiled), DIS's median over "
                f"{paper_analyses.DIS_TIMED_PAIRS} test pairs, on this suite's machine. The "
                "paper uses a PWC-Net pretrained on other data "
                f"({paper.TEXT['pwc_net_ms']} ms a pair on its GPU).\n\n"
            )
            network = result["methods"][flow_network.NETWORK]["epe"]
            dis = result["methods"][flow_network.STORED_FLOW]["epe"]
            holds = network < dis
            detail = f"{network:.3f} px against DIS's {dis:.3f} px ({network / dis:.2f}x)"
        return text + self._target(
            "flow_net",
            "the learned flow network's end-point error below DIS's",
            holds,
            detail + ".",
        )

    def flow_finetuning(self) -> str:
        """The paper's table "Fine-tuning Optical Flow" ("" in a suite without the further
        runs)."""
        if not self.scale.further:
            return ""
        table = "finetune_flow"
        text = "## 11. Fine-tuning optical flow\n\n"
        reference = self.mean_reference()
        epe = (self.results.get("flow_finetuning") or {}).get("epe", {})
        text += (
            "| method | Abs-Inv | Abs-Rel | S-RMSE | x mean | flow EPE after (px) | "
            f"{_paper_header(table)} |\n|---|---|---|---|---|---|---|---|\n"
        )
        for name in reversed(paper_suite.FLOW_EXPERIMENT):
            after = epe.get(name, {}).get("epe")
            ref = (table, name) if paper.row(table, name) else None
            text += _row(
                [
                    self._label(name),
                    *_cells(self.run(name), reference, self.missing_run(name)),
                    "—" if after is None else f"{after:.3f}",
                    _paper(ref, table),
                    _paper_x_mean(ref),
                ]
            )
        rate = self.scale.check_learning_rate or self.scale.learning_rate
        text += (
            "\nThe global-local model on the learned flow network's flow "
            "(`gld.models.flow_depth`), the network starting from section 10's: fixed, or "
            "fine-tuned end to end by the sparse depth loss; and the network followed by a "
            "(32, 16, 1) conv head trained by the sparse loss alone. Beside them the same "
            "model on the stored DIS flow. Every row: one pixel per image, "
            f"{self.scale.steps:,} steps, peak rate {rate:g}"
            + (
                ", the lower rate of the learning-rate check"
                if self.scale.check_learning_rate is not None
                else ""
            )
            + ", no epipolar term (it reads the stored flow); a row that collapsed says from "
            'which step. "flow EPE after": the run\'s flow network scored against the '
            "exact flow on the test pairs.\n\n"
        )
        fixed = _metric(self.run("flow_net_fixed"))
        finetuned = _metric(self.run("flow_net_finetuned"))
        holds, detail = None, "—"
        if fixed is not None and finetuned is not None:
            holds = fixed < finetuned
            detail = f"fixed {fixed:.4f}, fine-tuned {finetuned:.4f} Abs-Inv"
            head = _metric(self.run("flow_net_head"))
            if head is not None:
                detail += f", network + head {head:.4f}"
        return text + self._target(
            "finetuning",
            "the flow network fixed beats it fine-tuned by the sparse loss (the paper's ordering)",
            holds,
            detail + ".",
        )

    def ablations(self) -> str:
        table = "ablation_studies"
        rows = [(n, self.run(n), (table, n)) for n in ABLATION_ROWS]
        rows.append(("global_local_no_epipolar", self.run("global_local_no_epipolar"), None))
        text = "## 2. Ablations\n\n" + self._table(rows, table)
        text += (
            "\nThe full model here is the main job's: its global encoder sees the flow alone "
            '(beside it, the paper\'s "- Image Pair" row), so the image pair is the '
            "ablation added back (beside it, the paper's full model). The rows without a "
            "global module or without flow also drop what teaches g the motion (the epipolar "
            "term, the pose teacher and the refinement need g and read the flow); "
            '"- epipolar term, teacher and refinement" shows what those alone cost, and '
            "they are compared with it too.\n\n"
        )
        main = _metric(self.run("global_local_1px"))
        worse = {}
        for name in (
            "global_local_no_coordconv",
            "global_local_no_global_module",
            "global_local_no_flow",
        ):
            value = _metric(self.run(name))
            if value is not None and main is not None:
                worse[self.runs[name].label] = value / main - 1
        pair = _metric(self.run("global_local_image_pair"))
        if pair is not None and main is not None:
            worse["- image pair (the main model against + image pair)"] = main / pair - 1
        detail = "Abs-Inv change of each ablation against the main model: " + (
            ", ".join(f"{k} {v:+.1%}" for k, v in worse.items()) or "—"
        )
        # Without a global module or flow, the motion terms go too: such a row is worse
        # only if it is worse than the main model and than the main model without them.
        no_motion = _metric(self.run("global_local_no_epipolar"))
        against = {
            self.runs[name].label: value / no_motion - 1
            for name in ("global_local_no_global_module", "global_local_no_flow")
            if no_motion is not None and (value := _metric(self.run(name))) is not None
        }
        if against:
            detail += '; against "- epipolar term, teacher and refinement": ' + ", ".join(
                f"{k} {v:+.1%}" for k, v in against.items()
            )
        changes = [*worse.values(), *against.values()]
        holds = None if len(changes) < 6 else all(v > 0 for v in changes)
        return text + self._target(
            "ablations",
            "each ablation worse than the full model (the rows without the epipolar term "
            "also worse than the main model without it)",
            holds,
            detail + ".",
        )

    def density(self, figure_dir: Path) -> str:
        models = {
            "global_local": "global-local",
            "small_encdec": "Small Enc-Dec",
            "dispnet": "DispNet",
        }
        text = "## 3. Supervision density\n\n| method | " + " | ".join(
            paper_suite.density_name(d) for d in paper_suite.DENSITIES
        )
        table = "gt_density"
        text += f" | {_paper_header(table)} (1px → dense) |\n|---|"
        text += "---|" * (len(paper_suite.DENSITIES) + 2) + "\n"
        values: dict[str, list[float | None]] = {}
        labels, collapsed = {}, False
        for model, label in models.items():
            names = [self._density_run(model, d) for d in paper_suite.DENSITIES]
            values[model], cells = [], []
            for name in names:
                result = None if name is None else self.run(name)
                if result is not None and paper_suite.collapse(result) is not None:
                    collapsed = True
                    values[model].append(None)  # not drawn: a saturated output
                    cells.append(f"{_metric(result):.4f} (collapsed)")
                    continue
                values[model].append(_metric(result))
                cells.append(
                    "not in this suite"
                    if name is None
                    else self.missing_run(name)
                    if result is None
                    else f"{_metric(result):.4f} ({self._rate(name)})"
                )
            if model in paper_suite.LARGE_MODELS:
                label += f" ({self.scale.large_steps:,} steps)"
            labels[model] = label
            multiples = "—"
            if paper.row(table, model) is not None:
                multiples = " → ".join(
                    f"{paper.value(table, model, column) / paper.mean_value():.2f}"
                    for column in ("1px", "dense")
                )
            text += _row([label, *cells, _paper((table, model), table), multiples])
        text += (
            "\nAbs-Inv (the peak rate in brackets); columns: supervised pixels per image, and "
            "dense labels. Each model at every density trains at the rate its learning-rate "
            "check chose (section 1)"
            + ("; a collapsed run is not drawn" if collapsed else "")
            + ". A training image's supervised pixels are drawn again among its valid pixels "
            "each epoch.\n\n"
        )
        text += self._fixed_pixel()
        if any(v is not None for series in values.values() for v in series):
            path = figure_dir / "density.png"
            _draw_density(values, labels, path)
            text += f"![Abs-Inv against supervision density]({path.name})\n\n"
        ours, baseline = values["global_local"], values["small_encdec"]
        holds = None
        detail = "—"
        # The paper's one pixel against dense labels, in its Scenes11 column (its text's
        # 5% and 12% average over its datasets and metrics).
        theirs = {
            model: paper.value(table, model, "1px") / paper.value(table, model, "dense") - 1
            for model in paper.TABLES[table].rows
        }
        if None not in (ours[0], ours[-1], baseline[0], baseline[-1]):
            ours_loss, baseline_loss = ours[0] / ours[-1] - 1, baseline[0] / baseline[-1] - 1
            holds = ours_loss <= theirs["global_local"] and ours_loss < baseline_loss
            detail = (
                f"global-local's one-pixel error is {ours_loss:+.1%} against its dense error; "
                f"Small Enc-Dec's {baseline_loss:+.1%}"
            )
        text += self._target(
            "density",
            f"global-local's one-pixel error at most {theirs['global_local']:+.1%} against its "
            "dense error, and less above it than Small Enc-Dec's (the paper's Scenes11, "
            f"`{paper.TABLES[table].label}`: global-local {theirs['global_local']:+.1%}, "
            f"DispNet {theirs['dispnet']:+.1%})",
            holds,
            detail + ".",
        )
        return text

    def _fixed_pixel(self) -> str:
        """The one-fixed-pixel runs against the one-pixel column ("" if the suite has none)."""
        cells = []
        for model, name in paper_suite.FIXED_PIXEL_RUNS.items():
            if name not in self.runs:
                continue
            fixed, redrawn = self.run(name), self.run(self._density_run(model, 1) or "")
            label = self.runs[name].label.split(",")[0]
            if fixed is None:
                cells.append(f"{label} {self.missing_run(name)}")
                continue
            cells.append(
                f"{label} {_metric(fixed):.4f} ({self._rate(name)})"
                + (
                    f", {_metric(fixed) / _metric(redrawn) - 1:+.1%} against a pixel drawn "
                    f"again each epoch ({_metric(redrawn):.4f})"
                    if redrawn is not None
                    else ""
                )
            )
        if not cells:
            return ""
        return (
            "One fixed pixel per image, the same in every epoch (what a robot's range sensor "
            "gives: one measurement of each image): " + "; ".join(cells) + ".\n\n"
        )

    def _density_run(self, model: str, density: int) -> str | None:
        """The run of `model` at `density` the density table shows: at one pixel, the
        main table's run at its compared rate (the density runs train at that rate);
        None if the suite has none."""
        name = f"{model}_{paper_suite.density_name(density)}"
        if name not in self.runs:
            return None
        if name in self.checked:
            return self.compared_run(name) or name
        return name

    def given_flow_and_pose(self) -> str:
        table = "given_pose"
        rows = [
            (
                "triangulation_predicted_pose",
                self.results.get("triangulation_predicted_pose"),
                (table, "triangulation_predicted_pose"),
            ),
            (
                "triangulation_gt_pose",
                self.classical("triangulation_gt_pose"),
                (table, "triangulation_gt_pose"),
            ),
        ]
        rows += [
            (n, self.run(n), (table, n))
            for n in (
                "global_local_gt_flow",
                "global_local_gt_pose",
                "global_local_flow_pose",
                "global_local_1px",
            )
        ]
        text = "## 4. Given flow, given pose\n\n" + self._table(rows, table)
        return text + (
            "\nThe true pose enters the model as its global parameters: g = (10 x the "
            "rotation's vector part, the unit translation) replaces the global encoder's "
            "output (`--global_source=pose`, `gld.models.global_local.pose_parameters`); the "
            "local network "
            "and the hypernetwork are trained as usual. With `--global_source=flow_pose`, g "
            "is the pose the essential matrix gets from the model's own input flow "
            "(`gld.flow_pose`, the pose of `sfm_flow`): no label and no odometry. "
            "Triangulation with the predicted pose "
            "uses the pose the Pretrained-Full probe on the main run's encoder (section 6, "
            "first column) predicts for each test pair.\n\n"
        )

    def varying_intrinsics(self) -> str:
        table, fixed_table = "results_change_intrs", "results_sparse"
        text = "## 5. Varying intrinsics (±20% between views)\n\n"
        text += (
            "| method | fixed intrinsics | varying | change | x mean: fixed → varying | "
            f"{_paper_header(table).replace('paper', 'paper, varying', 1)} |\n"
            "|---|---|---|---|---|---|---|\n"
        )
        means = (self.mean_reference(), self.mean_reference(True))
        changes = {}

        def row(label, fixed, varying, ref=None, missing=(NOT_RUN, NOT_RUN)):
            change = None if None in (fixed, varying) else varying / fixed - 1
            relative = (
                f"{fixed / means[0]:.2f} → {varying / means[1]:.2f}"
                if None not in (fixed, varying, *means)
                else ""
            )
            cells = [
                absent if v is None else f"{v:.4f}"
                for v, absent in zip((fixed, varying), missing, strict=True)
            ]
            change = "" if change is None else f"{change:+.1%}"
            paper_cells = [_paper(ref, table, columns=1), _paper_x_mean(ref)]
            return _row([label, *cells, change, relative, *paper_cells])

        for model, label in (
            ("global_local", "global-local"),
            ("small_encdec", "Small Enc-Dec"),
            ("eigen", "Eigen"),
            ("dispnet", "DispNet"),
        ):
            name = f"{model}_varying"
            if name not in self.runs:
                continue
            fixed_run = self.compared_run(f"{model}_1px") or f"{model}_1px"
            fixed, varying = _metric(self.run(fixed_run)), _metric(self.run(name))
            if (result := self.run(name)) is not None and paper_suite.collapse(result) is not None:
                label += " — collapsed on the varying intrinsics"
            ref = (table, model) if paper.row(table, model) else None
            missing = (self.missing_run(fixed_run), self.missing_run(name))
            text += row(label, fixed, varying, ref, missing)
            changes[model] = (fixed, varying)
        for name in paper_analyses.CLASSICAL:
            fixed, varying = _metric(self.classical(name)), _metric(self.classical(name, True))
            text += row(CLASSICAL_LABELS[name], fixed, varying)
        # The paper's cost of varying intrinsics, its target: its model on Scenes11 in the
        # main table (fixed) and in the varying-intrinsics table.
        paper_fixed = paper.value(fixed_table, paper.TABLES[fixed_table].model)
        paper_varying = paper.value(table, "global_local")
        paper_change = paper_varying / paper_fixed - 1
        text += (
            "\nAbs-Inv, one pixel per image; each model trained and tested on "
            f"`{self.scale.varying_dataset}`, at the rate its learning-rate check chose "
            "(its fixed-intrinsics number is that run's). A varying pair is the fixed pair of "
            "the same index (scene, poses) seen through other intrinsics, so both columns "
            "score the same pairs; the first view's field of view changes, and with it the "
            "depth it sees, so the target reads the change of each model's Abs-Inv as a "
            "multiple of its split's dataset mean (the multiple of the oracle is given beside "
            "it). The learned models are not told the intrinsics; triangulation and SfM are "
            "given each view's true intrinsics, so their change is the estimated flow's: the "
            "change of camera between the views adds its own flow (the principal point moves "
            "by up to 20%), and the flow the models and the classical methods read is "
            'estimated on larger displacements. The paper\'s "x mean" is a multiple of its '
            "dataset mean with fixed intrinsics (it gives no other). The paper's text says "
            f"about {paper.TEXT['varying_increase_ours']:.0%} for its model; its Scenes11 "
            f"rows give {paper_fixed:.3f} fixed (`{paper.TABLES[fixed_table].label}`; "
            f"`{paper.TABLES[table].label}` has no fixed row) and {paper_varying:.3f} varying "
            f"(`{paper.TABLES[table].label}`): {paper_change:+.1%}.\n\n"
        )
        fixed, varying = changes.get("global_local", (None, None))
        holds, detail = None, "—"
        if None not in (fixed, varying, *means):
            relative = (varying / means[1]) / (fixed / means[0]) - 1
            holds = relative <= paper_change
            detail = (
                f"global-local {fixed:.4f} → {varying:.4f} ({varying / fixed - 1:+.1%}); the "
                f"dataset mean {means[0]:.4f} → {means[1]:.4f} "
                f"({means[1] / means[0] - 1:+.1%}); as a multiple of the mean "
                f"{fixed / means[0]:.2f} → {varying / means[1]:.2f} ({relative:+.1%})"
            )
            oracles = [self.oracle_reference(), self.oracle_reference(True)]
            if None not in oracles:
                detail += (
                    f"; as a multiple of the per-pair oracle constant {fixed / oracles[0]:.2f} "
                    f"→ {varying / oracles[1]:.2f} "
                    f"({(varying / oracles[1]) / (fixed / oracles[0]) - 1:+.1%})"
                )
        return text + self._target(
            "varying",
            f"varying intrinsics cost global-local at most {paper_change:+.1%}, the paper's "
            "Scenes11 (Abs-Inv as a multiple of each split's dataset mean)",
            holds,
            detail + ".",
        )

    def pose_probe(self) -> str:
        main, depth_only = paper_analyses.PROBED_RUNS
        text = "## 6. Pose from the global parameters (Sec. 4.4)\n\n"
        result = self.results.get("pose_probe")
        errors = {} if result is None else result["errors"]
        text += (
            "| probe | main run (motion terms): rotation / translation (deg) | run without "
            "the motion terms (depth loss alone) | paper (Scenes11, "
            f"`{paper.TABLES['pose_experiments'].label}`) |\n|---|---|---|---|\n"
        )
        scratch = errors.get(main, {})

        def cell(run_errors, setting):
            error = run_errors.get(setting) or (
                scratch.get(setting)
                if setting.startswith("scratch") or setting == "mean_pose"
                else None
            )
            if error is None:
                return self.missing("pose_probe")
            return f"{error['rotation_deg']:.2f} / {error['translation_deg']:.1f}"

        for setting, label in POSE_LABELS.items():
            text += _row(
                [
                    label,
                    cell(errors.get(main, {}), setting),
                    cell(errors.get(depth_only, {}), setting),
                    _paper(("pose_experiments", setting), "pose_experiments"),
                ]
            )
        text += (
            f"\nA two-hidden-layer MLP (256 units) on the six global parameters, "
            f"{self.scale.probe_steps:,} steps per setting on the training pairs; mean errors "
            "on the test pairs (`gld.analysis.probes`). The scratch rows are the same for both "
            "columns (a random encoder). The main run's motion terms (epipolar, pose "
            "teacher) train g to be the camera motion, so its encoder is expected to help; "
            "the paper's claim is about g learned from the depth loss alone, the second "
            "column, which the target reads.\n\n"
        )
        holds, detail = None, "—"
        pretrained = errors.get(depth_only, {})
        if "scratch_mlp" in scratch and "pretrained_mlp" in pretrained:
            mine, theirs = pretrained["pretrained_mlp"], scratch["scratch_mlp"]
            better = {
                key: mine[f"{key}_deg"] < theirs[f"{key}_deg"]
                for key in ("rotation", "translation")
            }
            holds = all(better.values())
            detail = (
                f"MLP only, encoder trained by the depth loss alone: rotation "
                f"{mine['rotation_deg']:.2f} against {theirs['rotation_deg']:.2f} deg from "
                f"scratch, translation {mine['translation_deg']:.1f} against "
                f"{theirs['translation_deg']:.1f} deg"
            )
            if len(set(better.values())) == 2:
                detail += (
                    " (mixed: "
                    + ", ".join(
                        f"{key} {'better' if b else 'not better'}" for key, b in better.items()
                    )
                    + ")"
                )
            if "scratch_full" in scratch and "pretrained_full" in pretrained:
                mine, theirs = pretrained["pretrained_full"], scratch["scratch_full"]
                detail += (
                    f"; all trained: {mine['rotation_deg']:.2f} / "
                    f"{mine['translation_deg']:.1f} against {theirs['rotation_deg']:.2f} / "
                    f"{theirs['translation_deg']:.1f}"
                )
        return text + self._target(
            "pose_probe",
            "the pretrained encoder's probe beats the scratch one (MLP only, the encoder of "
            "the run without the epipolar term; rotation and translation errors both lower)",
            holds,
            detail + ".",
        )

    def flow_error(self, figure_dir: Path) -> str:
        text = "## 7. Robustness to flow errors\n\n"
        result = self.results.get("flow_error")
        if result is None:
            return text + self.missing("flow_error") + ".\n\n"

        # Labelled as the tables label them; the model is the main run.
        main = f"{self.runs[paper_analyses.MAIN_RUN].label} (main run)"
        curves = {CLASSICAL_LABELS.get(n, main): c for n, c in result["curves"].items()}
        path = figure_dir / "flow_error.png"
        flow_error.draw_flow_error_curves(
            curves, path, title="per-pixel Abs-Inv against normalised flow error"
        )
        text += f"![per-pixel depth error against flow error]({path.name})\n\n"
        names = list(curves)
        text += "| normalised flow error | pixels | " + " | ".join(names) + " |\n"
        text += "|---|---|" + "---|" * len(names) + "\n"
        first = curves[names[0]]
        for index, count in enumerate(first["count"]):
            if not count:
                continue
            low, high = first["edges"][index], first["edges"][index + 1]
            cells = [
                f"{curves[n]['mean'][index]:.4f} ± {curves[n]['std'][index]:.4f}" for n in names
            ]
            text += _row([f"[{low:.2g}, {high:.2g})", f"{count:,}", *cells])
        text += (
            "\nPer-pixel Abs-Inv (mean ± std over the pixels of each bin) against the "
            "end-point error of the input flow, normalised by the image width and height "
            "(`gld.analysis.flow_error`); every test pixel with valid depth and true flow. The "
            "predicted pose is the Pretrained-Full probe's on the main run's encoder "
            "(section 6, first column).\n\n"
        )
        return text

    def overfitting(self, figure_dir: Path) -> str:
        text = "## 8. Loss on training points against held-out pixels\n\n"
        # The main-table runs evaluated over training (`Run.curve`), each at the rate its
        # comparisons use once its learning-rate check is done.
        drawn = [n for n, run in self.runs.items() if run.curve and n in self.checked]
        used = [self.compared_run(n) or n for n in drawn]
        curves = {name: self.run(name)["curves"] for name in used if self.run(name) is not None}
        if not curves:
            return text + NOT_RUN + ".\n\n"
        path = figure_dir / "overfitting.png"
        _draw_overfitting(curves, {n: self._label(n) for n in curves}, path)
        text += f"![training points against held-out pixels]({path.name})\n\n"
        text += "| run | training points, last | test, last |\n|---|---|---|\n"
        for name, curve in curves.items():
            train = np.mean([v for _, v in curve["train"][-5:]]) if curve["train"] else None
            test = curve["test"][-1][1] if curve["test"] else None
            text += _row(
                [
                    self._label(name),
                    "—" if train is None else f"{train:.4f}",
                    "—" if test is None else f"{test:.4f}",
                ]
            )
        pairs = self.scale.curve_examples
        return text + (
            "\nSolid: the L1 inverse-depth loss on the supervised pixels of the training "
            "batches (logged during training; the last five records averaged in the table); "
            "dashed: Abs-Inv over every pixel of the "
            + (f"first {pairs} test pairs" if pairs else "test pairs")
            + " (the same quantity on held-out pixels), evaluated during training.\n\n"
        )

    def qualitative(self, figure_dir: Path) -> str:
        text = "## 9. Qualitative results and generated filters\n\n"
        path = self.results_dir / "qualitative.npz"
        if self.results.get("qualitative") is None or not path.exists():
            text += f"Predictions: {self.missing('qualitative')}.\n\n"
        else:
            out = figure_dir / "qualitative.png"
            # Each column named by the run it shows, its label wrapped to the column.
            used = self.results["qualitative"]["runs"]
            labels = {n: textwrap.fill(self._label(run), 30) for n, run in used.items()}
            _draw_qualitative(path, labels, out)
            text += (
                f"![image, truth and predictions on test pairs]({out.name})\n\n"
                "Inverse depth, one colour scale for the whole grid.\n\n"
            )
        filters = self.results.get("filters")
        if filters is None:
            return text + f"Filters: {self.missing('filters')}.\n\n"
        for name in filters["figures"]:
            shutil.copyfile(self.results_dir / "figures" / name, figure_dir / name)
            text += f"![generated filters]({name})\n"
        correlation = filters["correlation"]
        return text + (
            "\nThe filter banks the global-local model generates for three test pairs: the "
            "first, the one whose motion is most similar to it, and the least similar. Over "
            f"the {correlation['num_pairs']} pairs of {filters['pairs']} test pairs, the "
            "similarity of two pairs' generated filters and of their camera motions have a "
            f"Pearson correlation of {correlation['pearson']:+.2f} and a Spearman correlation "
            f"of {correlation['spearman']:+.2f} (`gld.analysis.filter_inspection`).\n\n"
        )

    def budgets(self) -> str:
        text = "## Runs and budgets\n\n"
        text += (
            "| run | model | dataset | steps | batch | peak rate | supervised px | flow | "
            "parameters | train time |\n|---|---|---|---|---|---|---|---|---|---|\n"
        )
        for name, run in self.runs.items():
            result = self.run(name)
            if result is None:
                steps = paper_suite.run_steps(self.scale, run)
                missing = self.missing_run(name)
                text += _row([name, run.model, "", f"{steps:,}", "", "", "", "", "", missing])
                continue
            config = result["config"]
            seconds = result.get("train_seconds")
            text += _row(
                [
                    name,
                    run.model,
                    config["dataset"],
                    f"{config['steps']:,}",
                    config["batch_size"],
                    f"{config['learning_rate']:g}",
                    paper_suite.density_name(config["gt_pixels"]),
                    config["flow_source"],
                    f"{result['parameters']:,}",
                    "—" if seconds is None else f"{seconds / 60:.1f} min",
                ]
            )
        return text + "\n"


def write_report(
    scale: Scale,
    results: dict[str, dict],
    results_dir: str | Path,
    report_dir: str | Path,
    *,
    commit: str = "",
    command: str = "",
) -> Path:
    """Writes <report_dir>/README.md and its figures from the results (read from
    `results_dir`, which holds their arrays and figures); returns the README's path."""
    report_dir = Path(report_dir)
    report = Report(scale, results, results_dir, commit)
    # Checked and filled in before anything is written.
    path = report_dir / DISCUSSION
    discussion = report.fill_discussion(read_discussion(path), path)
    report_dir.mkdir(parents=True, exist_ok=True)
    results = report.results  # without those made by uncommitted code
    main = report.run("global_local_1px") or next(
        (r for k, r in results.items() if k.startswith("train/")), None
    )
    height = main["config"]["height"] if main else 0
    width = main["config"]["width"] if main else 0
    count = main["metrics"]["abs_inv"]["count"] if main else 0
    stamp = metrics.protocol_stamp(
        height,
        width,
        count,
        extra=(
            f"batch {scale.batch_size}, Adam at peak rate {scale.learning_rate:g}, warm-up "
            "then cosine decay, seed 0"
            + (
                "; self-supervised depth in units of its pose network's translation (||t|| = 1)"
                if scale.further
                else ""
            )
        ),
    )
    sections = [
        report.main_table(),
        report.ablations(),
        report.density(report_dir),
        report.given_flow_and_pose(),
        report.varying_intrinsics(),
        report.pose_probe(),
        report.flow_error(report_dir),
        report.overfitting(report_dir),
        report.qualitative(report_dir),
        report.learned_flow(report_dir),
        report.flow_finetuning(),
    ]
    finished = sum(1 for k in results if k.startswith("train/"))
    # A large baseline's step and the suite's whole budget of it, from the runner's times.
    large_step = [paper_runner.step_seconds(model) for model in paper_suite.LARGE_MODELS]
    budget = (
        f"{scale.steps:,} steps for every learned model"
        if scale.large_steps == scale.steps
        else (
            f"{scale.steps:,} steps for every learned model but DispNet and FCRN, which get "
            f"{scale.large_steps:,} (at {min(large_step):.0f}-{max(large_step):.0f} s a step on "
            f"this suite's machine, the full budget would take up to "
            f"{scale.steps * max(large_step) / 3600:.1f} hours each; their rows are "
            "reported, not counted in the main table's verdict)"
        )
    )
    commits = sorted({r.get("commit") for r in results.values() if r.get("commit")})
    rerun = ""
    if report.uncommitted:
        rerun = (
            (
                f"{len(report.uncommitted)} results were made by uncommitted code and are "
                if len(report.uncommitted) > 1
                else "1 result was made by uncommitted code and is "
            )
            + (
                "not reported"
                if report.refused
                else "reported here only because this report is made by uncommitted code too"
            )
            + "; each needs a re-run at a clean commit (delete its result, and a training "
            "run's directory, then run the suite again): "
            + ", ".join(f"`{task}` ({stamp})" for task, stamp in report.uncommitted.items())
            + ".\n\n"
        )
    # What the finished tasks took here: each one's wall time, or a resumed run's
    # training over all its launches (from its log) where that is longer.
    took = sum(max(r.get("seconds") or 0, r.get("train_seconds") or 0) for r in results.values())
    further = (
        ""
        if scale.further
        else " This suite leaves out the further runs (one fixed pixel per image, the "
        "self-supervised baseline, the learned flow network and its fine-tuning); the "
        "suites with them (`--suite=cpu_full`, `paper`) report those too."
    )
    try:
        where = (
            f"`{Path(results_dir).resolve().relative_to(report_dir.resolve())}/` beside this file"
        )
    except ValueError:
        where = f"`{results_dir}`"
    head = (
        f"# The paper's experiments on `{scale.dataset}` — suite `{scale.name}`\n\n"
        f"Made by `{command or 'python -m experiments.paper --suite=' + scale.name}`"
        f"{f' at commit {commit}' if commit else ''}; {finished} of {len(report.runs)} "
        f"training runs finished (results made at commit{'s' if len(commits) > 1 else ''} "
        f"{', '.join(commits) or '—'}). The suite takes {scale.hours}; its "
        f"{len(results)} finished tasks took {took / 3600:.1f} hours here.{further} Each "
        "task's result "
        f"is in {where}: `--report_only` rewrites this report from them, and the suite "
        "run beside them continues where they stop (an analysis whose run has a result but "
        "no checkpoint there retrains it with the same seed and notes it if it does not "
        "score its result).\n\n"
        f"{rerun}"
        f"{stamp[0].upper()}{stamp[1:]}\n\n"
        f"Budget: {budget}. Every learned model gets the same input pipeline, optimiser, "
        "peak learning rate, schedule, batch and seed, and the paper's loss (sparse L1 on "
        "inverse depth + edge-aware smoothness)"
        + (
            f"; the main table's models are trained at {scale.check_learning_rate:g} too "
            "(the learning-rate check, section 1). "
            if scale.check_learning_rate is not None
            else ". "
        )
        + "The global-local runs also carry the main "
        "job's recipe: a global module that learns the motion (the epipolar term at "
        f"{paper_suite.MAIN_MOTION_WEIGHTS['epipolar_weight']:g}, the classical pose teacher "
        f"at {paper_suite.MAIN_MOTION_WEIGHTS['pose_teacher_weight']:g}, "
        f"{paper_suite.MAIN_RECIPE['pose_refinement_steps']} refinement steps of the "
        "encoder's pose on the flow), a global "
        "encoder with instance normalisation that sees the flow alone, and the flow scaled "
        "by 10 as the model's input; the baselines see the image pair and the flow in "
        'pixels. "x mean" is Abs-Inv as a multiple of the dataset mean\'s ("paper x '
        "mean\": the paper's, as a multiple of the paper's dataset mean). "
        + _paper_sources()
        + "\n\n"
    )
    summary = "## Targets\n\n| target | verdict | numbers |\n|---|---|---|\n"
    for _, name, holds, detail in report.targets:
        summary += _row([name, _verdict(holds), detail])
    summary += _discussion(report.targets, discussion)
    retrained = [
        f"- `{task}`: {difference}\n"
        for task, result in sorted(results.items())
        for difference in result.get("retrained_differently", [])
    ]
    if retrained:
        summary += (
            "\nAnalyses that read a run retrained here (its checkpoint was not beside its "
            "result) that does not score its result exactly:\n\n" + "".join(retrained)
        )
    text = head + summary + "\n" + "".join(sections) + report.budgets()
    path = report_dir / "README.md"
    files_lib.write_atomically(path, text)
    return path


def _paper_placeholder(kind: str, args: list[str]) -> str:
    """A placeholder of the paper's numbers (`gld.paper.numbers`)."""
    table, *keys = args
    if table not in paper.TABLES or not keys or paper.row(table, keys[0]) is None:
        raise ValueError(f"{{{kind}:{':'.join(args)}}}: no such table or row of the paper")
    if kind == "paper":
        printed = paper.printed(table, keys[0])
        if len(keys) == 1:
            return " / ".join(printed)
        columns = paper.TABLES[table].columns
        if len(keys) != 2 or keys[1] not in columns:
            raise ValueError(f"{{{kind}:{':'.join(args)}}}: the columns are {columns}")
        return printed[columns.index(keys[1])]
    if kind == "paper_x_mean":
        return f"{paper.x_mean(table, keys[0]):.2f}x"
    if len(keys) != 2 or paper.row(table, keys[1]) is None:
        raise ValueError(f"{{{kind}:{':'.join(args)}}}: not {{{PLACEHOLDERS[kind]}}}")
    value, reference = paper.value(table, keys[0]), paper.value(table, keys[1])
    if kind == "paper_change":
        return f"{value / reference - 1:+.0%}"
    return f"{1 - value / reference:.0%}"  # paper_below


def _paper_sources() -> str:
    """Where the report's paper numbers come from, and the tables in which the paper gives
    its own model different numbers."""
    by_value: dict[float, list[str]] = {}
    for key, number in paper.model_values().items():
        by_value.setdefault(number, []).append(f"`{paper.TABLES[key].label}`")
    text = (
        "The paper's numbers are its Scenes11 column "
        f"({paper.TEXT['width']}x{paper.TEXT['height']}, {paper.TEXT['steps']:,} steps), "
        "each column of them naming the table of the paper it comes from"
    )
    if len(by_value) > 1:
        text += ": the paper gives its own model (one pixel per image) Abs-Inv " + "; ".join(
            f"{number:.3f} in {_and(tables)}" for number, tables in by_value.items()
        )
    return text + "."


def _and(items: Sequence[str]) -> str:
    """a, b and c."""
    return items[0] if len(items) == 1 else f"{', '.join(items[:-1])} and {items[-1]}"


def read_discussion(path: Path) -> dict[str, str]:
    """The hand-written discussion of a suite's targets: under a heading `## <key>` (a key
    of `TARGETS`), what explains that target's ordering. {} without the file."""
    if not path.exists():
        return {}
    parts = re.split(r"^## +(\S+) *$", path.read_text(), flags=re.MULTILINE)
    discussion = {key: text.strip() for key, text in zip(parts[1::2], parts[2::2], strict=True)}
    if unknown := sorted(set(discussion) - set(TARGETS)):
        raise ValueError(
            f"{path}: headings {unknown} name no target; the targets are {list(TARGETS)}"
        )
    if empty := sorted(key for key, text in discussion.items() if not text):
        raise ValueError(f"{path}: nothing under the headings {empty}")
    return discussion


def _discussion(
    targets: Sequence[tuple[str, str, bool | None, str]], discussion: dict[str, str]
) -> str:
    """What explains each ordering that does not hold, from the hand-written discussion
    beside the report; a target without its paragraph says so."""
    failed = [(key, name) for key, name, holds, _ in targets if holds is False]
    if not failed:
        return ""
    text = (
        "\n### What we think explains the orderings that do not hold\n\n"
        f"Written by hand (`{DISCUSSION}` beside this file, one `## <target>` section each: "
        f"{', '.join(f'`{key}`' for key in TARGETS)}); its numbers of this suite's runs "
        "and of the paper's tables are filled in from the results and `gld.paper.numbers` "
        "each time the report is written, and any other number it quotes (the paper's "
        "text, another suite, a run by hand) is marked as a quote in the file.\n\n"
    )
    for key, name in failed:
        text += f"**{name}** (`{key}`). {discussion.get(key, 'Not discussed yet.')}\n\n"
    return text


def _draw_density(values: dict[str, list], labels: dict[str, str], path: Path) -> None:
    plt = reports.pyplot()
    figure, axis = plt.subplots(figsize=(6, 3.5))
    positions = np.arange(len(paper_suite.DENSITIES))
    width = 0.8 / len(values)
    for index, (model, series) in enumerate(values.items()):
        heights = [np.nan if v is None else v for v in series]
        axis.bar(
            positions + (index - (len(values) - 1) / 2) * width, heights, width, label=labels[model]
        )
    axis.set_xticks(positions, [paper_suite.density_name(d) for d in paper_suite.DENSITIES])
    axis.set_xlabel("supervised pixels per image")
    axis.set_ylabel("Abs-Inv")
    # Room above the bars for the legend.
    drawn = [v for series in values.values() for v in series if v is not None]
    axis.set_ylim(0, 1.3 * max(drawn, default=1.0))
    axis.legend(loc="upper center", ncol=len(values), fontsize="small")
    axis.grid(axis="y", alpha=0.3)
    reports.save_figure(figure, path)


def _draw_overfitting(curves: dict[str, dict], labels: dict[str, str], path: Path) -> None:
    plt = reports.pyplot()
    figure, axis = plt.subplots(figsize=(6, 3.5))
    for index, (name, curve) in enumerate(curves.items()):
        colour = f"C{index}"
        if curve["train"]:
            steps, values = np.asarray(curve["train"]).T
            axis.plot(steps, values, color=colour, label=f"{labels[name]}: training points")
        if curve["test"]:
            steps, values = np.asarray(curve["test"]).T
            axis.plot(steps, values, "--o", color=colour, label=f"{labels[name]}: test pixels")
    axis.set_xlabel("training step")
    axis.set_ylabel("L1 inverse depth")
    axis.legend(fontsize=7)
    axis.grid(alpha=0.3)
    reports.save_figure(figure, path)


def _draw_qualitative(npz_path: Path, labels: dict[str, str], path: Path) -> None:
    plt = reports.pyplot()
    with np.load(npz_path) as arrays:
        arrays = dict(arrays)
    truth = np.where(
        arrays["depth_valid"], 1 / np.where(arrays["depth_valid"], arrays["depth"], 1), np.nan
    )
    limit = float(np.nanpercentile(truth, 99))
    columns = [("image 1", None), ("truth", truth)]
    columns += [
        (labels.get(n, n), arrays[n]) for n in paper_analyses.QUALITATIVE_RUNS if n in arrays
    ]
    rows = len(arrays["ids"])
    figure, axes = plt.subplots(
        rows, len(columns), figsize=(2.6 * len(columns), 2.0 * rows), squeeze=False
    )
    for row in range(rows):
        for column, (title, maps) in enumerate(columns):
            axis = axes[row, column]
            if maps is None:
                axis.imshow(np.clip(arrays["image1"][row] + 0.5, 0, 1))
            else:
                shown = axis.imshow(maps[row], cmap="magma", vmin=0, vmax=limit)
            if row == 0:
                axis.set_title(title, fontsize=8)
            axis.set_axis_off()
    figure.colorbar(shown, ax=axes.ravel().tolist(), fraction=0.02, label="inverse depth")
    reports.save_figure(figure, path, dpi=90)
