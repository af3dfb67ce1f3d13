"""Section 1 of the report: the main table (one supervised pixel per image), the
learning-rate check that picks the rate each model is compared at, and the main target."""

from __future__ import annotations

from gld.paper import analyses as paper_analyses
from gld.paper import numbers as paper
from gld.paper import rate_check, scales
from gld.paper.report_cells import metric, multiple_range, percent_range, table_row
from gld.paper.report_results import ReportResults

SUPERVISED_BASELINES = ("small_encdec_1px", "eigen_1px", "dispnet_1px", "fcrn_1px")
SELF_SUPERVISED = ("struct2depth", "struct2depth_flow")
# The main target: global-local this far below every learned baseline (a margin a little
# below the smallest of the paper's, which the target's name gives beside it).
MAIN_MARGIN = 0.15


def main_table(report: ReportResults) -> str:
    """The main table: each main-table model at the suite's rate, then at the rate of
    the learning-rate check, then the classical references. The paper's numbers sit
    on the row of the run each comparison uses (the rate the check chose; the suite's
    rate while the check is unfinished), so the other rate's row, which nothing
    compares, has none; the dataset mean's row has the paper's dataset mean."""
    table = "results_sparse"
    compared = {n: report.compared_run(n) or n for n in report.checked}
    rows = [(n, report.run(n), (table, n) if compared[n] == n else None) for n in report.checked]
    if report.scale.check_learning_rate is not None:
        for name in report.checked:
            low = rate_check.low_rate_name(name)
            rows.append((low, report.run(low), (table, name) if compared[name] == low else None))
    rows += [
        (n, report.classical(n), paper.MEAN if n == paper.MEAN[1] else None)
        for n in paper_analyses.CLASSICAL
    ]
    text = "## 1. Main table: one supervised pixel per image\n\n" + report.table(rows, table)
    text += "\n" + _paper_mean_note(report, table, compared) + "\n\n"
    if any(n in report.runs for n in SELF_SUPERVISED):
        text += (
            "The self-supervised baseline (Struct2Depth / monodepth2 family, "
            "`gld.models.baselines.self_supervised`) learns depth and pose from the image pair "
            "alone with a photometric reprojection loss (SSIM + L1, per-pixel minimum, "
            "auto-masking, edge-aware smoothness); no depth label. Its depth is scored in "
            "units of its pose network's translation (||t|| = 1, the paper's "
            "normalisation). Struct2Depth's object-motion model is left out: the scenes "
            "are static.\n\n"
        )
    text += learning_rate_check(report)
    compared = {n: report.compared_run(n) for n in report.checked}
    ours = metric(report.run(compared.get("global_local_1px") or ""))
    gaps, short = {}, {}
    for name in SUPERVISED_BASELINES:
        theirs = metric(report.run(compared.get(name, name) or ""))
        if ours is None or theirs is None:
            continue
        limited = report.scale.large_steps < report.scale.steps and (
            report.runs[name].model in scales.LARGE_MODELS
        )
        (short if limited else gaps)[report.runs[name].label] = 1 - ours / theirs
    expected = 2 if report.scale.large_steps < report.scale.steps else 4
    holds = None if len(gaps) < expected else all(g >= MAIN_MARGIN for g in gaps.values())
    detail = "global-local's Abs-Inv below each baseline's: " + (
        ", ".join(f"{name} {gap:.0%}" for name, gap in gaps.items()) or "—"
    )
    if report.scale.check_learning_rate is not None and ours is not None:
        detail += (
            " (each at the rate of the learning-rate check: "
            + ", ".join(
                f"{report.runs[n].label} {report.rate(r)}" for n, r in compared.items() if r
            )
            + ")"
        )
    if short:
        detail += "; at their shorter budget (not counted in the verdict): " + ", ".join(
            f"{name} {gap:.0%}" for name, gap in short.items()
        )
    unsupervised = {
        report.runs[n].label: 1 - ours / theirs
        for n in SELF_SUPERVISED
        if ours is not None
        and (run := compared.get(n)) is not None
        and (theirs := metric(report.run(run))) is not None
    }
    if unsupervised:
        detail += "; the self-supervised baselines (no depth labels; not counted): " + (
            ", ".join(f"{name} {gap:.0%}" for name, gap in unsupervised.items())
        )
    # The paper's margins over the same baselines, from its main table.
    model = paper.TABLES[table].model
    margins = [
        1 - paper.value(table, model) / paper.value(table, name) for name in SUPERVISED_BASELINES
    ]
    text += report.target(
        "main",
        f"global-local at least {MAIN_MARGIN:.0%} below every learned baseline with the "
        f"same budget (the paper's Scenes11: {percent_range(margins)})",
        holds,
        detail + ".",
    )
    return text


def _paper_mean_note(report: ReportResults, table: str, compared: dict[str, str]) -> str:
    """Where the main table's paper numbers come from, and the paper's models and ours
    as multiples of their dataset means."""
    mean_table = paper.MEAN[0]
    model = paper.TABLES[table].model
    text = (
        f"The paper's numbers: its Scenes11 column of `{paper.TABLES[table].label}`, "
        "beside the run each comparison uses"
        + (
            " (the rate the learning-rate check chose; the other rate's row has none)"
            if report.scale.check_learning_rate is not None
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
    theirs = [paper.x_mean(table, n) for n in labelled if n in report.runs]
    text += (
        ". \"paper x mean\" is the paper's Abs-Inv as a multiple of it: the paper's "
        f"models trained with depth labels score {multiple_range(theirs)} it"
    )
    reference = report.mean_reference()
    here = [metric(report.run(compared.get(n, n))) for n in labelled if n in report.runs]
    if reference and here and None not in here:
        multiples = [value / reference for value in here]
        text += f"; here the same models, at their compared rate, {multiple_range(multiples)}"
    return text + "."


def learning_rate_check(report: ReportResults) -> str:
    """The main table's models at the suite's rate and at the check's, the training
    loss that picks the compared one, and which runs collapsed."""
    if report.scale.check_learning_rate is None:
        return ""
    rates = (report.scale.learning_rate, report.scale.check_learning_rate)
    text = "### Learning-rate check\n\n| model | " + " | ".join(
        f"peak rate {rate:g}: test Abs-Inv / training loss" for rate in rates
    )
    text += " | compared at |\n|---|---|---|---|\n"
    for name in report.checked:
        cells = []
        for run_name in (name, rate_check.low_rate_name(name)):
            result = report.run(run_name)
            if result is None:
                cells.append(report.missing_run(run_name))
                continue
            loss = rate_check.training_loss(result)
            cell = f"{metric(result):.4f} / " + ("—" if loss is None else f"{loss:.4f}")
            if rate_check.collapse(result) is not None:
                cell += " (collapsed)"
            cells.append(cell)
        compared = report.compared_run(name)
        text += table_row(
            [report.runs[name].label, *cells, report.rate(compared) if compared else ""]
        )
    return text + (
        "\nOne shared rate can suit one model and starve another, so the main table's "
        "learned models are trained at two peak rates, and every comparison (the target "
        "below, the over-fitting figure, the qualitative grid) takes each at the rate "
        "with the lower training loss (the L1 "
        "inverse-depth loss on its supervised pixels over the last quarter of training, "
        "never the test split), unless that run collapsed and the other did not. A run "
        f'"collapsed" when its gradient norm is below {rate_check.VANISHED_GRADIENT:g} of '
        "its largest logged one at "
        "a quarter or more of its logged steps: its output saturated and it stopped "
        "learning. A model's runs at the other densities and on the varying intrinsics "
        "train at its compared rate too; the ablations, at the suite's rate.\n\n"
    )
