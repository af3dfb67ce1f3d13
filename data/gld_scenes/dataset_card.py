"""The `gld_scenes` dataset card: each pair's signal and flow error, summed up per split.

The builder writes the card into `metadata.json`: the surfaces' texture settings
(`texture_card`), and per split, from the first `CARD_PAIRS` pairs, what the pairs offer
a depth learner (`signal_statistics`, summed up by `summarise_signal`) and the estimated
flow's error by texture kind (`flow_error_by_texture`, `summarise_texture_errors`).
Numpy and OpenCV only, so each pair's part runs in the rendering workers.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

from gld import geometry
from gld.evaluation import metrics
from gld.models.baselines import classical

from . import scenes, textures

# The card's signal statistics come from the first CARD_PAIRS pairs of each split (pairs
# are independent draws), so they cost seconds even for `full`.
CARD_PAIRS = 500
# The card's classical pipeline: `sfm_flow`'s pose estimate (numpy and OpenCV only, so it
# runs in the rendering workers); its fallback is never used here (a failed pair is
# counted, not scored).
_SFM_FLOW = classical.SfMFlow(fallback_inv_depth=1.0)


def texture_card(surface_detail: bool) -> dict[str, Any]:
    """What the card says of the surfaces' texture: the kinds and, with surface detail,
    its settings (`textures.SurfaceDetail`)."""
    card: dict[str, Any] = {"kinds": list(textures.TEXTURES), "surface_detail": surface_detail}
    if surface_detail:
        card.update(
            detail_spacings_m=list(textures.DETAIL_SPACINGS),
            detail_persistence=textures.DETAIL_PERSISTENCE,
            detail_contrast=scenes.DETAIL_CONTRAST,
            detail_fade_pixels=list(textures.DETAIL_FADE_PIXELS),
            note="value noise fixed to each surface multiplies its albedo by 1 + contrast * "
            "d (d in [-1, 1]); an octave of lattice spacing s fades out as s shrinks from "
            "the second to the first fade value in pixels on the surface",
        )
    return card


def signal_statistics(example: Mapping[str, Any]) -> dict[str, float]:
    """What one pair offers a depth learner: its motion, its parallax, its triangulability.

    Numpy only (it runs in the rendering workers). The triangulation is the
    `triangulation_gt_pose` baseline's (`classical.triangulate_batch`) and its Abs-Inv
    follows the evaluation's protocol, so the card's numbers are the ones
    `python -m experiments.evaluate --model=triangulation_gt_pose` reports.

    Args:
      example: a raw example or a stored record: 'depth1' [H, W]; 'flow' (the estimate)
        and 'gt_flow' [H, W, 2] pixels I1 -> I2; 'gt_flow_valid' [H, W] bool;
        'intrinsics1', 'intrinsics2' [4] normalised; 'rotation' [3, 3]; 'translation' [3].

    Returns:
      gt_flow_px_mean, gt_flow_px_median: |true flow| in pixels over its valid pixels;
      translational_flow_px_mean: |true flow - rotation-only flow| over the same pixels,
        where the rotation-only flow is the pair's flow with the translation set to zero
        (the flow at infinite depth), so the rest is the parallax that carries depth;
      triangulation_abs_inv_estimated_flow, triangulation_abs_inv_gt_flow: Abs-Inv of
        triangulation with the true pose from each flow, over every valid depth pixel,
        depth scaled so that ||t|| = 1;
      triangulation_scale_log_error_estimated_flow: log of the pair's median
        triangulated inverse depth (true pose, estimated flow) over its median true
        inverse depth: how well the estimated flow fixes the pair's depth scale even
        given the pose;
      oracle_constant_abs_inv: Abs-Inv of the pair's own median true inverse depth
        predicted everywhere (the per-pair oracle constant of the evaluations);
      sfm_flow_failed: 1 when the classical pipeline (`classical.SfMFlow`: essential
        matrix from the estimated flow) finds no pose, else 0;
      sfm_flow_rotation_deg, sfm_flow_translation_deg: its pose's rotation and
        translation-direction errors, and sfm_flow_abs_inv: Abs-Inv of triangulation
        with that pose (as the `sfm_flow` baseline predicts it); NaN when it failed
        (the evaluation then predicts the dataset mean).
      The flow values are NaN for a pair without a valid true-flow pixel.
    """
    depth = np.asarray(example["depth1"], np.float64)
    height, width = depth.shape
    intrinsics1 = np.asarray(example["intrinsics1"], np.float64)
    intrinsics2 = np.asarray(example["intrinsics2"], np.float64)
    rotation = np.asarray(example["rotation"], np.float64)
    translation = np.asarray(example["translation"], np.float64)
    gt_flow = np.asarray(example["gt_flow"], np.float64)
    flow_valid = np.asarray(example["gt_flow_valid"], bool)
    camera_matrix1 = geometry.intrinsics_matrix(intrinsics1, height, width)
    camera_matrix2 = geometry.intrinsics_matrix(intrinsics2, height, width)

    rotational_flow, _ = geometry.depth_to_flow(
        np.ones_like(depth), camera_matrix1, camera_matrix2, rotation, np.zeros(3)
    )
    magnitude = np.linalg.norm(gt_flow, axis=-1)[flow_valid]
    parallax = np.linalg.norm(gt_flow - rotational_flow, axis=-1)[flow_valid]

    sfm_rotation, sfm_translation, sfm_found = _SFM_FLOW.estimate_pose(
        np.asarray(example["flow"], np.float64), camera_matrix1, camera_matrix2
    )

    def thrice(value):
        return np.stack([np.asarray(value, np.float32)] * 3)

    # One batch of three: the estimated flow, then the true flow, with the true pose; the
    # estimated flow with sfm_flow's pose.
    predicted = classical.triangulate_batch(
        np.stack([example["flow"], example["gt_flow"], example["flow"]]).astype(np.float32),
        thrice(intrinsics1),
        thrice(intrinsics2),
        np.stack([rotation, rotation, sfm_rotation]).astype(np.float32),
        np.stack([translation, translation, sfm_translation]).astype(np.float32),
    )["inv_depth"]
    depth_valid = geometry.valid_depth(depth)
    true_inv_depth = np.linalg.norm(translation) / depth[depth_valid]
    abs_inv = [np.abs(true_inv_depth - pair[depth_valid]).mean() for pair in predicted]
    sfm_errors = metrics.pose_errors(sfm_rotation, sfm_translation, rotation, translation)
    nan = float("nan")
    true_median = np.median(true_inv_depth)
    scale_log_error = np.log(np.median(predicted[0][depth_valid]) / true_median)
    has_flow = bool(flow_valid.any())
    return {
        "gt_flow_px_mean": float(magnitude.mean()) if has_flow else nan,
        "gt_flow_px_median": float(np.median(magnitude)) if has_flow else nan,
        "translational_flow_px_mean": float(parallax.mean()) if has_flow else nan,
        "triangulation_abs_inv_estimated_flow": float(abs_inv[0]),
        "triangulation_abs_inv_gt_flow": float(abs_inv[1]),
        "triangulation_scale_log_error_estimated_flow": float(scale_log_error),
        "oracle_constant_abs_inv": float(np.abs(true_inv_depth - true_median).mean()),
        "sfm_flow_failed": float(not sfm_found),
        "sfm_flow_rotation_deg": float(sfm_errors["rotation_deg"]) if sfm_found else nan,
        "sfm_flow_translation_deg": float(sfm_errors["translation_deg"]) if sfm_found else nan,
        "sfm_flow_abs_inv": float(abs_inv[2]) if sfm_found else nan,
    }


def flow_error_by_texture(example: Mapping[str, Any]) -> dict[str, tuple[float, int]]:
    """The estimated flow's end-point error summed over the valid true-flow pixels of each
    texture kind of view 1's surface, and their count: {kind: (error sum px, pixels)}.

    Args:
      example: 'flow', 'gt_flow' [H, W, 2]; 'gt_flow_valid' [H, W] bool; 'texture_kind1'
        [H, W] int (an index into `textures.TEXTURES`, as `renderer.render_pair` gives it).
    """
    valid = np.asarray(example["gt_flow_valid"], bool)
    error = np.linalg.norm(
        np.asarray(example["flow"], np.float64) - np.asarray(example["gt_flow"], np.float64),
        axis=-1,
    )
    kinds = np.asarray(example["texture_kind1"])
    return {
        kind: (float(error[valid & (kinds == index)].sum()), int((valid & (kinds == index)).sum()))
        for index, kind in enumerate(textures.TEXTURES)
    }


def summarise_texture_errors(per_pair: list[dict[str, tuple[float, int]]]) -> dict[str, Any]:
    """The card's `flow_epe_by_texture_<split>` from `flow_error_by_texture` of some pairs:
    per texture kind, the mean end-point error over its pixels and its share of them."""
    total = sum(count for pair in per_pair for _, count in pair.values())
    summary: dict[str, Any] = {
        "pairs": len(per_pair),
        "note": "estimated flow's end-point error (px) over the valid true-flow pixels of "
        "each texture kind of view 1's surface (pixel-weighted), and the kind's share of "
        "those pixels",
    }
    for kind in textures.TEXTURES:
        error_sum = sum(pair[kind][0] for pair in per_pair)
        count = sum(pair[kind][1] for pair in per_pair)
        summary[kind] = {
            "epe_px": error_sum / count if count else None,
            "pixel_share": count / total if total else None,
        }
    return summary


def summarise_signal(per_pair: list[dict[str, float]], split_pairs: int) -> dict[str, Any]:
    """The card's `signal_<split>` entry from `signal_statistics` of some of its pairs.

    Every value is the mean over pairs of the per-pair value, except gt_flow_px_median,
    the median over pairs of each pair's median; a log error also gets its standard
    deviation over pairs (`<name>_std`: the spread a per-pair scale keeps once a
    constant bias is removed). Pairs without a valid true-flow pixel are left out of
    the flow values.
    """
    summary: dict[str, Any] = {
        "pairs": len(per_pair),
        "split_pairs": split_pairs,
        "note": (
            f"over the first {len(per_pair)} of {split_pairs} pairs: means over pairs of "
            "per-pair values (gt_flow_px_median: the median of the pairs' medians); flow in "
            "pixels over valid true-flow pixels; translational = true flow minus the "
            "rotation-only flow (zero translation); triangulation with the true pose, "
            "Abs-Inv at ||t|| = 1 over valid depth pixels; scale log error: log(median "
            "triangulated / median true inverse depth), mean and std over pairs"
        ),
    }
    for name in per_pair[0] if per_pair else ():
        values = np.asarray([pair[name] for pair in per_pair], np.float64)
        values = values[np.isfinite(values)]
        reduce = np.median if name == "gt_flow_px_median" else np.mean
        summary[name] = float(reduce(values)) if values.size else None
        if "log_error" in name:
            summary[f"{name}_std"] = float(values.std()) if values.size else None
    return summary
