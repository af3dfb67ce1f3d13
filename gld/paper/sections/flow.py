"""The report's sections on optical flow: the depth error against the input flow's error
(section 7), the learned flow network against DIS (section 10) and the flow network fixed
or fine-tuned by the depth loss (section 11), with their targets."""

from __future__ import annotations

from pathlib import Path

from gld.analysis import flow_error as flow_error_lib
from gld.evaluation import flow_network
from gld.paper import analyses as paper_analyses
from gld.paper import numbers as paper
from gld.paper import run_configs
from gld.paper import suite as paper_suite
from gld.paper.report_cells import (
    metric,
    metric_cells,
    paper_cell,
    paper_header,
    paper_x_mean_cell,
    table_row,
)
from gld.paper.report_results import CLASSICAL_LABELS, ReportResults


def flow_error(report: ReportResults, figure_dir: Path) -> str:
    text = "## 7. Robustness to flow errors\n\n"
    result = report.results.get("flow_error")
    if result is None:
        return text + report.missing("flow_error") + ".\n\n"

    # Labelled as the tables label them; the model is the main run.
    main = f"{report.runs[paper_analyses.MAIN_RUN].label} (main run)"
    curves = {CLASSICAL_LABELS.get(n, main): c for n, c in result["curves"].items()}
    path = figure_dir / "flow_error.png"
    flow_error_lib.draw_flow_error_curves(
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
        cells = [f"{curves[n]['mean'][index]:.4f} ± {curves[n]['std'][index]:.4f}" for n in names]
        text += table_row([f"[{low:.2g}, {high:.2g})", f"{count:,}", *cells])
    text += (
        "\nPer-pixel Abs-Inv (mean ± std over the pixels of each bin) against the "
        "end-point error of the input flow, normalised by the image width and height "
        "(`gld.analysis.flow_error`); every test pixel with valid depth and true flow. The "
        "predicted pose is the Pretrained-Full probe's on the main run's encoder "
        "(section 6, first column).\n\n"
    )
    return text


def learned_flow(report: ReportResults, figure_dir: Path) -> str:
    """The learned flow network against DIS: end-point error and speed ("" in a suite
    without the further runs)."""
    if not report.scale.further:
        return ""
    text = "## 10. Learned optical flow\n\n"
    result = report.results.get("flow_net")
    holds, detail = None, "—"
    if result is None:
        text += report.missing("flow_net") + ".\n\n"
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
            text += table_row(
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
        recipe = run_configs.flow_net_config(report.scale, height=0, width=0)
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
    return text + report.target(
        "flow_net",
        "the learned flow network's end-point error below DIS's",
        holds,
        detail + ".",
    )


def flow_finetuning(report: ReportResults) -> str:
    """The paper's table "Fine-tuning Optical Flow" ("" in a suite without the further
    runs)."""
    if not report.scale.further:
        return ""
    table = "finetune_flow"
    text = "## 11. Fine-tuning optical flow\n\n"
    reference = report.mean_reference()
    epe = (report.results.get("flow_finetuning") or {}).get("epe", {})
    text += (
        "| method | Abs-Inv | Abs-Rel | S-RMSE | x mean | flow EPE after (px) | "
        f"{paper_header(table)} |\n|---|---|---|---|---|---|---|---|\n"
    )
    for name in reversed(paper_suite.FLOW_EXPERIMENT):
        after = epe.get(name, {}).get("epe")
        ref = (table, name) if paper.row(table, name) else None
        text += table_row(
            [
                report.label(name),
                *metric_cells(report.run(name), reference, report.missing_run(name)),
                "—" if after is None else f"{after:.3f}",
                paper_cell(ref, table),
                paper_x_mean_cell(ref),
            ]
        )
    rate = report.scale.check_learning_rate or report.scale.learning_rate
    text += (
        "\nThe global-local model on the learned flow network's flow "
        "(`gld.models.flow_depth`), the network starting from section 10's: fixed, or "
        "fine-tuned end to end by the sparse depth loss; and the network followed by a "
        "(32, 16, 1) conv head trained by the sparse loss alone. Beside them the same "
        "model on the stored DIS flow. Every row: one pixel per image, "
        f"{report.scale.steps:,} steps, peak rate {rate:g}"
        + (
            ", the lower rate of the learning-rate check"
            if report.scale.check_learning_rate is not None
            else ""
        )
        + ", no epipolar term (it reads the stored flow); a row that collapsed says from "
        'which step. "flow EPE after": the run\'s flow network scored against the '
        "exact flow on the test pairs.\n\n"
    )
    fixed = metric(report.run("flow_net_fixed"))
    finetuned = metric(report.run("flow_net_finetuned"))
    holds, detail = None, "—"
    if fixed is not None and finetuned is not None:
        holds = fixed < finetuned
        detail = f"fixed {fixed:.4f}, fine-tuned {finetuned:.4f} Abs-Inv"
        head = metric(report.run("flow_net_head"))
        if head is not None:
            detail += f", network + head {head:.4f}"
    return text + report.target(
        "finetuning",
        "the flow network fixed beats it fine-tuned by the sparse loss (the paper's ordering)",
        holds,
        detail + ".",
    )
