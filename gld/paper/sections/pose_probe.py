"""Section 6 of the report: the camera pose read from the global parameters by a probe,
pretrained encoder against scratch, and the pose-probe target (the paper's Sec. 4.4)."""

from __future__ import annotations

from gld.paper import analyses as paper_analyses
from gld.paper import numbers as paper
from gld.paper.report_cells import paper_cell, table_row
from gld.paper.report_results import ReportResults

POSE_LABELS = {
    "scratch_mlp": "Scratch-MLP (random encoder, MLP trained)",
    "pretrained_mlp": "Pretrained-MLP (the trained model's encoder, MLP trained)",
    "scratch_full": "Scratch-Full (random encoder, all trained)",
    "pretrained_full": "Pretrained-Full (the trained model's encoder, all trained)",
    "mean_pose": "the test pairs' mean pose (a reference that sees the truth)",
}


def pose_probe(report: ReportResults) -> str:
    main, depth_only = paper_analyses.PROBED_RUNS
    text = "## 6. Pose from the global parameters (Sec. 4.4)\n\n"
    result = report.results.get("pose_probe")
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
            return report.missing("pose_probe")
        return f"{error['rotation_deg']:.2f} / {error['translation_deg']:.1f}"

    for setting, label in POSE_LABELS.items():
        text += table_row(
            [
                label,
                cell(errors.get(main, {}), setting),
                cell(errors.get(depth_only, {}), setting),
                paper_cell(("pose_experiments", setting), "pose_experiments"),
            ]
        )
    text += (
        f"\nA two-hidden-layer MLP (256 units) on the six global parameters, "
        f"{report.scale.probe_steps:,} steps per setting on the training pairs; mean errors "
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
            key: mine[f"{key}_deg"] < theirs[f"{key}_deg"] for key in ("rotation", "translation")
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
                + ", ".join(f"{key} {'better' if b else 'not better'}" for key, b in better.items())
                + ")"
            )
        if "scratch_full" in scratch and "pretrained_full" in pretrained:
            mine, theirs = pretrained["pretrained_full"], scratch["scratch_full"]
            detail += (
                f"; all trained: {mine['rotation_deg']:.2f} / "
                f"{mine['translation_deg']:.1f} against {theirs['rotation_deg']:.2f} / "
                f"{theirs['translation_deg']:.1f}"
            )
    return text + report.target(
        "pose_probe",
        "the pretrained encoder's probe beats the scratch one (MLP only, the encoder of "
        "the run without the epipolar term; rotation and translation errors both lower)",
        holds,
        detail + ".",
    )
