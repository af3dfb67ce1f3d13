"""Section 4 of the report: the model given the true flow, the true pose or its flow's
essential-matrix pose, beside triangulation with a true or predicted pose."""

from __future__ import annotations

from gld.paper.report_results import ReportResults


def given_flow_and_pose(report: ReportResults) -> str:
    table = "given_pose"
    rows = [
        (
            "triangulation_predicted_pose",
            report.results.get("triangulation_predicted_pose"),
            (table, "triangulation_predicted_pose"),
        ),
        (
            "triangulation_gt_pose",
            report.classical("triangulation_gt_pose"),
            (table, "triangulation_gt_pose"),
        ),
    ]
    rows += [
        (n, report.run(n), (table, n))
        for n in (
            "global_local_gt_flow",
            "global_local_gt_pose",
            "global_local_flow_pose",
            "global_local_1px",
        )
    ]
    text = "## 4. Given flow, given pose\n\n" + report.table(rows, table)
    return text + (
        "\nThe true pose enters the model as its global parameters: g = (10 x the "
        "rotation's vector part, the unit translation) replaces the global encoder's "
        "output (`--global_source=pose`, `gld.models.global_local.pose_parameters`); the "
        "local network "
        "and the hypernetwork are trained as usual, and, as in the main recipe, the local "
        "network sees the flow less the flow of that pose's rotation and the flow "
        "triangulated under it (the paper's Ours-GT Pose gives it the flow itself). "
        "With `--global_source=flow_pose`, g "
        "is the pose the essential matrix gets from the model's own input flow "
        "(`gld.flow_pose`, the pose of `sfm_flow`): no label and no odometry. "
        "Triangulation with the predicted pose "
        "uses the pose the Pretrained-Full probe on the main run's encoder (section 6, "
        "first column) predicts for each test pair.\n\n"
    )
