"""Tests of the gld_scenes dataset card's per-pair numbers and summaries
(data/gld_scenes/dataset_card.py) on hand-made pairs."""

import numpy as np
import pytest

from data.gld_scenes import dataset_card
from gld import geometry

HEIGHT, WIDTH = 48, 64


def _moving_pair(rotation, translation, seed=0):
    """A hand-made example: random depth 2-6 m seen by a camera that moves by (R, t), its
    exact flow and an estimate off by 0.5 px."""
    rng = np.random.default_rng(seed)
    depth = rng.uniform(2.0, 6.0, (HEIGHT, WIDTH))
    intrinsics = np.array([0.9, 1.2, 0.5, 0.5])
    camera_matrix = geometry.intrinsics_matrix(intrinsics, HEIGHT, WIDTH)
    gt_flow, _ = geometry.depth_to_flow(depth, camera_matrix, camera_matrix, rotation, translation)
    return {
        "depth1": depth.astype(np.float32),
        "flow": (gt_flow + 0.5).astype(np.float32),
        "gt_flow": gt_flow.astype(np.float32),
        "gt_flow_valid": np.ones((HEIGHT, WIDTH), bool),
        "intrinsics1": intrinsics,
        "intrinsics2": intrinsics,
        "rotation": np.asarray(rotation, np.float64),
        "translation": np.asarray(translation, np.float64),
    }


def test_signal_of_a_pure_translation_is_all_parallax():
    example = _moving_pair(np.eye(3), np.array([0.3, 0.1, 0.05]))
    signal = dataset_card.signal_statistics(example)
    magnitude = np.linalg.norm(example["gt_flow"], axis=-1)
    assert signal["gt_flow_px_mean"] == pytest.approx(magnitude.mean(), rel=1e-6)
    assert signal["gt_flow_px_median"] == pytest.approx(np.median(magnitude), rel=1e-6)
    assert signal["translational_flow_px_mean"] == pytest.approx(magnitude.mean(), rel=1e-5)
    assert signal["triangulation_abs_inv_gt_flow"] < 1e-5
    assert signal["triangulation_abs_inv_estimated_flow"] > 100 * max(
        signal["triangulation_abs_inv_gt_flow"], 1e-6
    )


def test_signal_scale_error_and_oracle_constant_by_hand():
    example = _moving_pair(np.eye(3), np.array([0.3, 0.0, 0.0]))
    true_inv_depth = 0.3 / example["depth1"].astype(np.float64)
    oracle = np.abs(true_inv_depth - np.median(true_inv_depth)).mean()
    exact = dataset_card.signal_statistics({**example, "flow": example["gt_flow"]})
    assert exact["triangulation_scale_log_error_estimated_flow"] == pytest.approx(0.0, abs=1e-4)
    assert exact["oracle_constant_abs_inv"] == pytest.approx(oracle, rel=1e-6)
    # A sideways translation: twice the flow is twice the parallax, so twice the inverse
    # depth everywhere (log 2).
    doubled = dataset_card.signal_statistics({**example, "flow": 2.0 * example["gt_flow"]})
    assert doubled["triangulation_scale_log_error_estimated_flow"] == pytest.approx(
        np.log(2.0), abs=1e-3
    )


def test_signal_of_a_pure_rotation_has_no_parallax():
    rotation = geometry.rotation_matrix(np.radians([1.0, 2.0, 0.5]))
    example = _moving_pair(rotation, np.array([1e-9, 0.0, 0.0]))
    signal = dataset_card.signal_statistics(example)
    assert signal["gt_flow_px_mean"] > 1.0
    assert signal["translational_flow_px_mean"] < 1e-4
    # No translation: the classical pipeline's pose (and so its values) may be undefined.
    assert all(
        np.isfinite(value) for name, value in signal.items() if not name.startswith("sfm_flow")
    )


def test_signal_scores_the_classical_pipeline_on_the_estimated_flow():
    rotation = geometry.rotation_matrix(np.radians([1.0, -2.0, 0.5]))
    example = _moving_pair(rotation, np.array([0.3, 0.1, 0.05]))
    exact = dataset_card.signal_statistics({**example, "flow": example["gt_flow"]})
    assert exact["sfm_flow_failed"] == 0.0
    assert exact["sfm_flow_rotation_deg"] < 0.05
    assert exact["sfm_flow_translation_deg"] < 0.5
    assert exact["sfm_flow_abs_inv"] < 1e-3
    # A flow that is off by a constant half pixel gives a worse pose and depth.
    shifted = dataset_card.signal_statistics(example)
    assert shifted["sfm_flow_translation_deg"] > 10 * exact["sfm_flow_translation_deg"]
    assert shifted["sfm_flow_abs_inv"] > 10 * exact["sfm_flow_abs_inv"]
    # No motion: no pose, counted as a failure and not scored.
    still = dataset_card.signal_statistics({**example, "flow": np.zeros_like(example["gt_flow"])})
    assert still["sfm_flow_failed"] == 1.0
    assert np.isnan(still["sfm_flow_abs_inv"]) and np.isnan(still["sfm_flow_rotation_deg"])


def test_flow_error_by_texture_sums_each_kind_over_valid_pixels():
    gt_flow = np.zeros((2, 3, 2), np.float32)
    flow = gt_flow.copy()
    flow[..., 0] = [[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]]
    valid = np.array([[True, True, True], [True, True, False]])
    kinds = np.array([[0, 0, 1], [1, 4, 4]])  # plain, plain, checker / checker, noise, noise
    errors = dataset_card.flow_error_by_texture(
        {"flow": flow, "gt_flow": gt_flow, "gt_flow_valid": valid, "texture_kind1": kinds}
    )
    assert errors["plain"] == (3.0, 2)
    assert errors["checker"] == (7.0, 2)
    assert errors["noise"] == (5.0, 1)  # the invalid pixel is left out
    assert errors["stripes"] == (0.0, 0)
    summary = dataset_card.summarise_texture_errors([errors, errors])
    assert summary["plain"] == {"epe_px": 1.5, "pixel_share": 0.4}
    assert summary["noise"] == {"epe_px": 5.0, "pixel_share": 0.2}
    assert summary["stripes"] == {"epe_px": None, "pixel_share": 0.0}


def test_signal_summary_counts_pairs_and_skips_pairs_without_flow():
    per_pair = [
        {"gt_flow_px_mean": 2.0, "gt_flow_px_median": 1.0, "triangulation_abs_inv_gt_flow": 0.1},
        {"gt_flow_px_mean": 4.0, "gt_flow_px_median": 3.0, "triangulation_abs_inv_gt_flow": 0.2},
        {"gt_flow_px_mean": 9.0, "gt_flow_px_median": 8.0, "triangulation_abs_inv_gt_flow": 0.6},
        {
            "gt_flow_px_mean": float("nan"),
            "gt_flow_px_median": float("nan"),
            "triangulation_abs_inv_gt_flow": 0.3,
        },
    ]
    summary = dataset_card.summarise_signal(per_pair, split_pairs=10)
    assert summary["pairs"] == 4 and summary["split_pairs"] == 10
    assert "first 4 of 10 pairs" in summary["note"]
    assert summary["gt_flow_px_mean"] == pytest.approx(5.0)
    assert summary["gt_flow_px_median"] == pytest.approx(3.0)  # median of 1, 3, 8
    assert summary["triangulation_abs_inv_gt_flow"] == pytest.approx(0.3)
    errors = dataset_card.summarise_signal(
        [{"scale_log_error": value} for value in (0.1, 0.3, 0.5)], split_pairs=3
    )
    assert errors["scale_log_error"] == pytest.approx(0.3)
    assert errors["scale_log_error_std"] == pytest.approx(np.std([0.1, 0.3, 0.5]))
