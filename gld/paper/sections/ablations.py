"""Section 2 of the report: the ablations against the full model, and their target."""

from __future__ import annotations

from gld.paper.report_cells import metric
from gld.paper.report_results import ReportResults

ABLATION_ROWS = (
    "global_local_1px",
    "global_local_image_pair",
    "global_local_no_coordconv",
    "global_local_no_global_module",
    "global_local_no_flow",
)


def ablations(report: ReportResults) -> str:
    table = "ablation_studies"
    rows = [(n, report.run(n), (table, n)) for n in ABLATION_ROWS]
    rows.append(("global_local_no_epipolar", report.run("global_local_no_epipolar"), None))
    text = "## 2. Ablations\n\n" + report.table(rows, table)
    text += (
        "\nThe full model here is the main job's: its global encoder sees the flow alone "
        '(beside it, the paper\'s "- Image Pair" row), so the image pair is the '
        "ablation added back (beside it, the paper's full model). The rows without a "
        "global module or without flow also drop what teaches g the motion (the epipolar "
        "term, the pose teacher and the refinement need g and read the flow); "
        '"- epipolar term, teacher and refinement" shows what those alone cost, and '
        "they are compared with it too.\n\n"
    )
    main = metric(report.run("global_local_1px"))
    worse = {}
    for name in (
        "global_local_no_coordconv",
        "global_local_no_global_module",
        "global_local_no_flow",
    ):
        value = metric(report.run(name))
        if value is not None and main is not None:
            worse[report.runs[name].label] = value / main - 1
    pair = metric(report.run("global_local_image_pair"))
    if pair is not None and main is not None:
        worse["- image pair (the main model against + image pair)"] = main / pair - 1
    detail = "Abs-Inv change of each ablation against the main model: " + (
        ", ".join(f"{k} {v:+.1%}" for k, v in worse.items()) or "—"
    )
    # Without a global module or flow, the motion terms go too: such a row is worse
    # only if it is worse than the main model and than the main model without them.
    no_motion = metric(report.run("global_local_no_epipolar"))
    against = {
        report.runs[name].label: value / no_motion - 1
        for name in ("global_local_no_global_module", "global_local_no_flow")
        if no_motion is not None and (value := metric(report.run(name))) is not None
    }
    if against:
        detail += '; against "- epipolar term, teacher and refinement": ' + ", ".join(
            f"{k} {v:+.1%}" for k, v in against.items()
        )
    changes = [*worse.values(), *against.values()]
    holds = None if len(changes) < 6 else all(v > 0 for v in changes)
    return text + report.target(
        "ablations",
        "each ablation worse than the full model (the rows without the epipolar term "
        "also worse than the main model without it)",
        holds,
        detail + ".",
    )
