"""The report's figure sections: the loss on training points against held-out pixels
(section 8), and the qualitative grid with the generated filters (section 9); each
figure drawn here."""

from __future__ import annotations

import shutil
import textwrap
from pathlib import Path

import numpy as np

from gld.evaluation import reports
from gld.paper import analyses as paper_analyses
from gld.paper.report_cells import NOT_RUN, table_row
from gld.paper.report_results import ReportResults


def overfitting(report: ReportResults, figure_dir: Path) -> str:
    text = "## 8. Loss on training points against held-out pixels\n\n"
    # The main-table runs evaluated over training (`Run.curve`), each at the rate its
    # comparisons use once its learning-rate check is done.
    drawn = [n for n, run in report.runs.items() if run.curve and n in report.checked]
    used = [report.compared_run(n) or n for n in drawn]
    curves = {name: report.run(name)["curves"] for name in used if report.run(name) is not None}
    if not curves:
        return text + NOT_RUN + ".\n\n"
    path = figure_dir / "overfitting.png"
    _draw_overfitting(curves, {n: report.label(n) for n in curves}, path)
    text += f"![training points against held-out pixels]({path.name})\n\n"
    text += "| run | training points, last | test, last |\n|---|---|---|\n"
    for name, curve in curves.items():
        train = np.mean([v for _, v in curve["train"][-5:]]) if curve["train"] else None
        test = curve["test"][-1][1] if curve["test"] else None
        text += table_row(
            [
                report.label(name),
                "—" if train is None else f"{train:.4f}",
                "—" if test is None else f"{test:.4f}",
            ]
        )
    pairs = report.scale.curve_examples
    return text + (
        "\nSolid: the L1 inverse-depth loss on the supervised pixels of the training "
        "batches (logged during training; the last five records averaged in the table); "
        "dashed: Abs-Inv over every pixel of the "
        + (f"first {pairs} test pairs" if pairs else "test pairs")
        + " (the same quantity on held-out pixels), evaluated during training.\n\n"
    )


def qualitative(report: ReportResults, figure_dir: Path) -> str:
    text = "## 9. Qualitative results and generated filters\n\n"
    path = report.results_dir / "qualitative.npz"
    if report.results.get("qualitative") is None or not path.exists():
        text += f"Predictions: {report.missing('qualitative')}.\n\n"
    else:
        out = figure_dir / "qualitative.png"
        # Each column named by the run it shows, its label wrapped to the column.
        used = report.results["qualitative"]["runs"]
        labels = {n: textwrap.fill(report.label(run), 30) for n, run in used.items()}
        _draw_qualitative(path, labels, out)
        text += (
            f"![image, truth and predictions on test pairs]({out.name})\n\n"
            "Inverse depth, one colour scale for the whole grid.\n\n"
        )
    filters = report.results.get("filters")
    if filters is None:
        return text + f"Filters: {report.missing('filters')}.\n\n"
    for name in filters["figures"]:
        shutil.copyfile(report.results_dir / "figures" / name, figure_dir / name)
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
