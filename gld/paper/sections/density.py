"""Section 3 of the report: Abs-Inv against the supervised pixels per image (a table and
its figure), the one-fixed-pixel control, and the density target."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from gld.evaluation import reports
from gld.paper import numbers as paper
from gld.paper import rate_check, scales
from gld.paper import suite as paper_suite
from gld.paper.report_cells import metric, paper_cell, paper_header, table_row
from gld.paper.report_results import ReportResults


def density(report: ReportResults, figure_dir: Path) -> str:
    models = {
        "global_local": "global-local",
        "small_encdec": "Small Enc-Dec",
        "dispnet": "DispNet",
    }
    text = "## 3. Supervision density\n\n| method | " + " | ".join(
        paper_suite.density_name(d) for d in scales.DENSITIES
    )
    table = "gt_density"
    text += f" | {paper_header(table)} (1px → dense) |\n|---|"
    text += "---|" * (len(scales.DENSITIES) + 2) + "\n"
    values: dict[str, list[float | None]] = {}
    labels, collapsed = {}, False
    for model, label in models.items():
        names = [_density_run(report, model, d) for d in scales.DENSITIES]
        values[model], cells = [], []
        for name in names:
            result = None if name is None else report.run(name)
            if result is not None and rate_check.collapse(result) is not None:
                collapsed = True
                values[model].append(None)  # not drawn: a saturated output
                cells.append(f"{metric(result):.4f} (collapsed)")
                continue
            values[model].append(metric(result))
            cells.append(
                "not in this suite"
                if name is None
                else report.missing_run(name)
                if result is None
                else f"{metric(result):.4f} ({report.rate(name)})"
            )
        if model in scales.LARGE_MODELS:
            label += f" ({report.scale.large_steps:,} steps)"
        labels[model] = label
        multiples = "—"
        if paper.row(table, model) is not None:
            multiples = " → ".join(
                f"{paper.value(table, model, column) / paper.mean_value():.2f}"
                for column in ("1px", "dense")
            )
        text += table_row([label, *cells, paper_cell((table, model), table), multiples])
    text += (
        "\nAbs-Inv (the peak rate in brackets); columns: supervised pixels per image, and "
        "dense labels. Each model at every density trains at the rate its learning-rate "
        "check chose (section 1)"
        + ("; a collapsed run is not drawn" if collapsed else "")
        + ". A training image's supervised pixels are drawn again among its valid pixels "
        "each epoch.\n\n"
    )
    text += _fixed_pixel(report)
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
    text += report.target(
        "density",
        f"global-local's one-pixel error at most {theirs['global_local']:+.1%} against its "
        "dense error, and less above it than Small Enc-Dec's (the paper's Scenes11, "
        f"`{paper.TABLES[table].label}`: global-local {theirs['global_local']:+.1%}, "
        f"DispNet {theirs['dispnet']:+.1%})",
        holds,
        detail + ".",
    )
    return text


def _fixed_pixel(report: ReportResults) -> str:
    """The one-fixed-pixel runs against the one-pixel column ("" if the suite has none)."""
    cells = []
    for model, name in paper_suite.FIXED_PIXEL_RUNS.items():
        if name not in report.runs:
            continue
        fixed, redrawn = report.run(name), report.run(_density_run(report, model, 1) or "")
        label = report.runs[name].label.split(",")[0]
        if fixed is None:
            cells.append(f"{label} {report.missing_run(name)}")
            continue
        cells.append(
            f"{label} {metric(fixed):.4f} ({report.rate(name)})"
            + (
                f", {metric(fixed) / metric(redrawn) - 1:+.1%} against a pixel drawn "
                f"again each epoch ({metric(redrawn):.4f})"
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


def _density_run(report: ReportResults, model: str, density: int) -> str | None:
    """The run of `model` at `density` the density table shows: at one pixel, the
    main table's run at its compared rate (the density runs train at that rate);
    None if the suite has none."""
    name = f"{model}_{paper_suite.density_name(density)}"
    if name not in report.runs:
        return None
    if name in report.checked:
        return report.compared_run(name) or name
    return name


def _draw_density(values: dict[str, list], labels: dict[str, str], path: Path) -> None:
    plt = reports.pyplot()
    figure, axis = plt.subplots(figsize=(6, 3.5))
    positions = np.arange(len(scales.DENSITIES))
    width = 0.8 / len(values)
    for index, (model, series) in enumerate(values.items()):
        heights = [np.nan if v is None else v for v in series]
        axis.bar(
            positions + (index - (len(values) - 1) / 2) * width, heights, width, label=labels[model]
        )
    axis.set_xticks(positions, [paper_suite.density_name(d) for d in scales.DENSITIES])
    axis.set_xlabel("supervised pixels per image")
    axis.set_ylabel("Abs-Inv")
    # Room above the bars for the legend.
    drawn = [v for series in values.values() for v in series if v is not None]
    axis.set_ylim(0, 1.3 * max(drawn, default=1.0))
    axis.legend(loc="upper center", ncol=len(values), fontsize="small")
    axis.grid(axis="y", alpha=0.3)
    reports.save_figure(figure, path)
