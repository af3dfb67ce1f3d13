"""The report of a suite (`gld.paper.runner`): every table of the paper's experimental
section with our numbers beside the paper's, the orderings it claims checked, and the
figures as PNG.

    <report_dir>/README.md     the tables, targets, budgets, protocol, commit
    <report_dir>/*.png         density, flow errors, over-fitting, qualitative grid, filters,
                               the pair-by-pair comparison with sfm_flow

The paper's numbers all come from `gld.paper.numbers` (its Scenes11 column, by table of
the paper), and each column of them names its table: the paper gives its own model
different numbers in different tables. A run or analysis not finished yet appears as
"not run yet". A result made by uncommitted code (its commit stamp ends with "+changes")
is listed as needing a re-run at a clean commit, and a report made at a clean commit does
not report it (`gld.paper.report_results.ReportResults`).

`write_report` writes the head (protocol, budget, commits), the targets' verdicts, the
sections (`gld.paper.sections`: each a function of the results the report reads) and
the table of runs and budgets. The hand-written discussion beside the report
(`discussion.md`, `gld.paper.discussion`) writes the suite's numbers as placeholders that
the report fills in from the results, and marks any other number it quotes; a number
written by hand is an error.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

from gld import files as files_lib
from gld.evaluation import metrics
from gld.paper import numbers as paper
from gld.paper import run_configs, scales
from gld.paper import suite as paper_suite
from gld.paper.discussion import discussion_section, report_discussion
from gld.paper.report_cells import table_row, verdict
from gld.paper.report_results import ReportResults
from gld.paper.scales import Scale
from gld.paper.sections.ablations import ablations
from gld.paper.sections.density import density
from gld.paper.sections.figures import overfitting, qualitative
from gld.paper.sections.flow import flow_error, flow_finetuning, learned_flow
from gld.paper.sections.given_flow_and_pose import given_flow_and_pose
from gld.paper.sections.main_table import main_table
from gld.paper.sections.pose_probe import pose_probe
from gld.paper.sections.regimes import regimes
from gld.paper.sections.varying_intrinsics import varying_intrinsics
from gld.paper.tasks import step_seconds
from gld.runs import recipe


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
    report = ReportResults(scale, results, results_dir, commit)
    # Checked and filled in before anything is written.
    discussion = report_discussion(report, report_dir)
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
        main_table(report),
        ablations(report),
        density(report, report_dir),
        given_flow_and_pose(report),
        varying_intrinsics(report),
        pose_probe(report),
        flow_error(report, report_dir),
        overfitting(report, report_dir),
        qualitative(report, report_dir),
        learned_flow(report, report_dir),
        flow_finetuning(report),
        regimes(report, report_dir),
    ]
    finished = sum(1 for k in results if k.startswith("train/"))
    # A large baseline's step and the suite's whole budget of it, from the runner's times.
    large_step = [step_seconds(model) for model in scales.LARGE_MODELS]
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
        f"{recipe.MOTION_WEIGHTS['epipolar_weight']:g}, the classical pose teacher "
        f"at {recipe.MOTION_WEIGHTS['pose_teacher_weight']:g}, "
        f"a search of {recipe.ARCHITECTURE['pose_refinement_starts']} translation "
        f"directions and {recipe.ARCHITECTURE['pose_refinement_steps']} refinement steps "
        "of the encoder's pose on the flow, whose rotation's flow is subtracted from the local "
        "network's and under which the flow is triangulated for it), a global "
        "encoder with instance normalisation that sees the flow alone, and the flow scaled "
        "by 10 as the model's input; the baselines see the image pair and the flow in "
        'pixels. "x mean" is Abs-Inv as a multiple of the dataset mean\'s ("paper x '
        "mean\": the paper's, as a multiple of the paper's dataset mean). "
        + _paper_sources()
        + "\n\n"
    )
    summary = "## Targets\n\n| target | verdict | numbers |\n|---|---|---|\n"
    for _, name, holds, detail in report.targets:
        summary += table_row([name, verdict(holds), detail])
    summary += discussion_section(report.targets, discussion)
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
    text = head + summary + "\n" + "".join(sections) + _budgets(report)
    path = report_dir / "README.md"
    files_lib.write_atomically(path, text)
    return path


def _budgets(report: ReportResults) -> str:
    """Every run of the suite: its model, data, budget, rate, supervision, flow, size and
    training time."""
    text = "## Runs and budgets\n\n"
    text += (
        "| run | model | dataset | steps | batch | peak rate | supervised px | flow | "
        "parameters | train time |\n|---|---|---|---|---|---|---|---|---|---|\n"
    )
    for name, run in report.runs.items():
        result = report.run(name)
        if result is None:
            steps = run_configs.run_steps(report.scale, run)
            missing = report.missing_run(name)
            text += table_row([name, run.model, "", f"{steps:,}", "", "", "", "", "", missing])
            continue
        config = result["config"]
        seconds = result.get("train_seconds")
        text += table_row(
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
