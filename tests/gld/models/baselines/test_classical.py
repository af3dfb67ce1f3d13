import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from gld import geometry
from gld.models import layers
from gld.models.baselines import classical

HEIGHT, WIDTH = 48, 64
INTRINSICS1 = np.array([0.9, 1.2, 0.5, 0.5])
INTRINSICS2 = np.array([0.95, 1.15, 0.48, 0.52])


def _scene_batch(seed=0, batch_size=2, translation_norm=1.0):
    """Non-planar scenes (independent random depth per pixel) seen by a moving camera,
    with exact flow; depth is in the contract's scale (divided by ||t||)."""
    rng = np.random.default_rng(seed)
    depth = rng.uniform(2.0, 6.0, (batch_size, HEIGHT, WIDTH)) * translation_norm
    rotation = geometry.rotation_matrix(rng.normal(0.0, 0.05, (batch_size, 3)))
    direction = rng.normal(0.0, 1.0, (batch_size, 3)) * [1.0, 0.5, 0.3]
    translation = direction / np.linalg.norm(direction, axis=-1, keepdims=True)
    translation = translation * translation_norm
    camera_matrix1 = geometry.intrinsics_matrix(INTRINSICS1, HEIGHT, WIDTH)
    camera_matrix2 = geometry.intrinsics_matrix(INTRINSICS2, HEIGHT, WIDTH)
    flow, depth2 = geometry.depth_to_flow(
        depth, camera_matrix1, camera_matrix2, rotation, translation
    )
    assert np.all(depth2 > 0)
    return {
        "flow": flow.astype(np.float32),
        "depth": (depth / translation_norm).astype(np.float32),
        "intrinsics1": np.tile(INTRINSICS1, (batch_size, 1)).astype(np.float32),
        "intrinsics2": np.tile(INTRINSICS2, (batch_size, 1)).astype(np.float32),
        "rotation": rotation.astype(np.float32),
        "translation": translation.astype(np.float32),
    }


def test_triangulation_with_true_pose_recovers_depth_in_unit_baseline_scale():
    # ||t|| = 3: the prediction must be the depth of the scene scaled to ||t|| = 1.
    batch = _scene_batch(translation_norm=3.0)
    outputs = classical.TriangulationGtPose().predict(batch)
    assert outputs["inv_depth"].shape == (2, HEIGHT, WIDTH)
    np.testing.assert_array_equal(outputs["untriangulated"], [0, 0])
    assert outputs["triangulated"].all()
    relative_error = np.abs(outputs["depth"] - batch["depth"]) / batch["depth"]
    assert relative_error.max() < 1e-3


def test_triangulation_is_jittable_over_jax_arrays():
    batch = _scene_batch(seed=1)
    keys = ["flow", "intrinsics1", "intrinsics2", "rotation", "translation"]
    outputs = jax.jit(classical.triangulate_batch)(*(jnp.asarray(batch[key]) for key in keys))
    relative_error = jnp.abs(outputs["depth"] - batch["depth"]) / batch["depth"]
    assert float(relative_error.max()) < 1e-3


def test_triangulation_of_numpy_arrays_stays_in_numpy_and_matches_the_jitted_one():
    batch = _scene_batch(seed=6)
    batch["flow"][0, :4] = np.nan  # filled with the pair median
    batch["flow"][1] = np.nan  # nothing triangulates: the fallback, without a warning
    keys = ["flow", "intrinsics1", "intrinsics2", "rotation", "translation"]
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        outputs = classical.triangulate_batch(*(batch[key] for key in keys))
    assert all(type(value) is np.ndarray for value in outputs.values())
    jitted = classical.TriangulationGtPose().predict(batch)
    np.testing.assert_array_equal(outputs["triangulated"], jitted["triangulated"])
    np.testing.assert_array_equal(outputs["untriangulated"], [4 * WIDTH, HEIGHT * WIDTH])
    np.testing.assert_allclose(outputs["inv_depth"], jitted["inv_depth"], rtol=1e-4)
    np.testing.assert_allclose(outputs["inv_depth"][1], layers.INITIAL_INV_DEPTH)


def test_untriangulable_pixels_get_the_pair_median_and_are_counted():
    batch = _scene_batch(seed=2)
    flow = batch["flow"].copy()
    flow[0, :4] = np.nan  # non-finite flow: 4 rows of pair 0
    flow[1] = np.nan  # nothing usable in pair 1
    outputs = classical.TriangulationGtPose().predict({**batch, "flow": flow})
    assert np.all(np.isfinite(outputs["inv_depth"])) and np.all(outputs["inv_depth"] > 0)
    np.testing.assert_array_equal(outputs["untriangulated"], [4 * WIDTH, HEIGHT * WIDTH])
    np.testing.assert_allclose(
        outputs["inv_depth"][0, :4], np.median(1.0 / batch["depth"][0, 4:]), rtol=1e-4
    )
    np.testing.assert_allclose(outputs["inv_depth"][1], layers.INITIAL_INV_DEPTH)


def test_points_behind_the_camera_are_not_triangulated():
    batch = _scene_batch(seed=3, batch_size=1)
    # Flow reversed: the rays now meet behind camera 1 for most pixels.
    outputs = classical.TriangulationGtPose().predict({**batch, "flow": -batch["flow"]})
    assert outputs["untriangulated"][0] > 0
    assert np.all(np.isfinite(outputs["depth"])) and np.all(outputs["depth"] > 0)


def _assert_pose_within(outputs, batch, *, rotation_degrees, translation_degrees):
    """Every pair succeeded, with its estimated pose within the given errors of the truth."""
    assert not outputs["failed"].any()
    rotation_error = geometry.rotation_error_degrees(outputs["rotation"], batch["rotation"])
    assert np.all(rotation_error < rotation_degrees), rotation_error
    translation_error = geometry.translation_error_degrees(
        outputs["translation"], batch["translation"]
    )
    assert np.all(translation_error < translation_degrees), translation_error


def test_sfm_on_exact_flow_recovers_pose_and_depth():
    batch = _scene_batch(seed=4)
    outputs = classical.SfMFlow(fallback_inv_depth=0.1).predict(batch)
    _assert_pose_within(outputs, batch, rotation_degrees=1.0, translation_degrees=2.0)
    np.testing.assert_allclose(np.linalg.norm(outputs["translation"], axis=-1), 1.0, rtol=1e-5)
    # The scale is fixed by ||t|| = 1, the contract's scale: depth is directly comparable.
    relative_error = np.abs(outputs["depth"] - batch["depth"]) / batch["depth"]
    assert np.median(relative_error) < 1e-2, np.median(relative_error)


def test_sfm_pose_is_refined_on_every_inlier_of_noisy_flow_with_outliers():
    # A minimal-sample RANSAC model carries the noise of its five correspondences; the
    # estimate must be refined on all inliers (and ignore the gross outliers).
    batch = _scene_batch(seed=5, batch_size=4)
    rng = np.random.default_rng(0)
    flow = batch["flow"] + rng.normal(0.0, 0.1, batch["flow"].shape)
    outliers = rng.random(flow.shape[:3]) < 0.1
    flow[outliers] += rng.uniform(-8.0, 8.0, (outliers.sum(), 2))
    batch["flow"] = flow.astype(np.float32)
    outputs = classical.SfMFlow(fallback_inv_depth=0.1).predict(batch)
    _assert_pose_within(outputs, batch, rotation_degrees=0.5, translation_degrees=0.5)


def test_sfm_failure_is_flagged_and_predicted_not_dropped():
    batch = _scene_batch(seed=5)
    batch["flow"][1] = 0.0  # no parallax: the pose is undetermined
    method = classical.SfMFlow()
    assert method.needs_training_data
    with pytest.raises(ValueError, match="call fit"):
        method.predict(batch)
    # The fallback is the training mean inverse depth: 1/4 here.
    method.fit([{"depth": np.full((3, 4, 4), 4.0)}])
    outputs = method.predict(batch)
    np.testing.assert_array_equal(outputs["failed"], [False, True])
    assert outputs["inv_depth"].shape == (2, HEIGHT, WIDTH)
    np.testing.assert_allclose(outputs["inv_depth"][1], 0.25)
    assert outputs["untriangulated"][1] == HEIGHT * WIDTH
    assert np.all(np.isfinite(outputs["inv_depth"]))


def test_dataset_mean_over_valid_pixels_in_unit_baseline_scale():
    valid = np.ones((4, 4), bool)
    valid[:2] = False
    examples = [
        # inverse depth 0.5 on 16 pixels
        {"depth": np.full((4, 4), 2.0), "translation": np.array([1.0, 0.0, 0.0])},
        # depth 8 at ||t|| = 2 is depth 4 at ||t|| = 1: inverse 0.25, on 8 valid pixels
        {
            "depth": np.where(valid, 8.0, 0.0),
            "depth_valid": valid,
            "translation": np.array([0.0, 2.0, 0.0]),
        },
    ]
    method = classical.DatasetMean().fit(examples)
    assert method.inv_depth == pytest.approx((16 * 0.5 + 8 * 0.25) / 24)
    outputs = method.predict({"flow": np.zeros((3, 5, 6, 2), np.float32)})
    assert outputs["inv_depth"].shape == (3, 5, 6)
    np.testing.assert_allclose(outputs["depth"], 1.0 / method.inv_depth, rtol=1e-6)


def test_oracle_predicts_each_pair_median_true_inverse_depth_over_valid_pixels():
    depth = np.array(
        [
            # Valid inverse depths 0.1, 0.2, 0.4 -> 0.2. With the two pixels marked invalid
            # (inverse 1 and 2) the median would be 0.4; with the zero depth, 0.3.
            [[10.0, 5.0, 2.5], [1.0, 0.5, 0.0]],
            # Valid 0.1, 0.2, 0.4, 0.5 -> 0.3 (an even count); inf and -1 are invalid.
            [[10.0, 5.0, 2.5], [2.0, np.inf, -1.0]],
        ]
    )
    depth_valid = np.array(
        [
            [[True, True, True], [False, False, True]],
            [[True, True, True], [True, True, True]],
        ]
    )
    method = classical.CLASSICAL["oracle_pair_median"]()
    assert not method.needs_training_data
    outputs = method.predict({"depth": depth, "depth_valid": depth_valid})
    assert outputs["inv_depth"].shape == (2, 2, 3) and outputs["inv_depth"].dtype == np.float32
    np.testing.assert_allclose(outputs["inv_depth"][0], 0.2, rtol=1e-6)
    np.testing.assert_allclose(outputs["inv_depth"][1], 0.3, rtol=1e-6)
    np.testing.assert_allclose(outputs["depth"], 1.0 / outputs["inv_depth"])


def test_oracle_without_depth_valid_uses_valid_depth_and_falls_back_on_empty_pairs():
    depth = np.zeros((2, 1, 4))
    depth[0] = [[10.0, 0.0, 5.0, 2.5]]  # 0.1, 0.2, 0.4; the 0 is invalid
    outputs = classical.OraclePairMedian(fallback_inv_depth=0.3).predict({"depth": depth})
    np.testing.assert_allclose(outputs["inv_depth"][0], 0.2, rtol=1e-6)
    np.testing.assert_allclose(outputs["inv_depth"][1], 0.3, rtol=1e-6)
    assert np.all(np.isfinite(outputs["depth"]))


def test_the_references_are_labelled_as_references():
    assert "oracle" in classical.LABELS["oracle_pair_median"]
    assert "sees the truth" in classical.LABELS["oracle_pair_median"]
    assert "same flow" in classical.LABELS["sfm_flow"]
    assert "no training" in classical.LABELS["sfm_flow"]
    assert set(classical.LABELS) <= set(classical.CLASSICAL)


def test_every_method_follows_one_protocol_and_rejects_bad_batches():
    for name, method_class in classical.CLASSICAL.items():
        method = method_class()
        assert isinstance(method.needs_training_data, bool), name
        with pytest.raises(ValueError, match="flow"):
            method.predict({"flow": np.zeros((4, 4, 2))})
    with pytest.raises(ValueError, match="call fit"):
        classical.DatasetMean().predict({"flow": np.zeros((1, 4, 4, 2))})
    with pytest.raises(ValueError, match="rotation"):
        classical.TriangulationGtPose().predict(
            {"flow": np.zeros((1, 4, 4, 2)), "intrinsics1": np.zeros((1, 4))}
        )
    with pytest.raises(ValueError, match="no valid depth"):
        classical.DatasetMean().fit([{"depth": np.zeros((2, 2))}])
    with pytest.raises(ValueError, match="depth"):
        classical.OraclePairMedian().predict({"depth": np.ones((4, 4))})
