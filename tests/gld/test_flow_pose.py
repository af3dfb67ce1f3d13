"""The essential-matrix pose from a flow field (`gld.flow_pose`) and its use as the
model's global parameters (`global_source="flow_pose"`)."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
import pytest

from gld import flow_pose, geometry
from gld.models import global_local as model_lib
from gld.models import registry
from gld.runs import state

HEIGHT, WIDTH = 48, 64


def _pair(rotation_vector, translation, seed=0):
    """Exact flow of a slanted, bumpy surface seen by two cameras with the given motion."""
    rng = np.random.default_rng(seed)
    intrinsics1 = np.array([0.9, 1.2, 0.5, 0.5])
    intrinsics2 = np.array([0.92, 1.18, 0.48, 0.52])
    grid = geometry.pixel_grid(HEIGHT, WIDTH).astype(np.float64)
    depth = 3.0 + 0.02 * grid[..., 0] + 0.5 * np.sin(grid[..., 1] / 5.0) + rng.uniform(0, 0.3)
    rotation = geometry.rotation_matrix(np.asarray(rotation_vector, np.float64))
    translation = np.asarray(translation, np.float64)
    flow, _ = geometry.depth_to_flow(
        depth,
        geometry.intrinsics_matrix(intrinsics1, HEIGHT, WIDTH),
        geometry.intrinsics_matrix(intrinsics2, HEIGHT, WIDTH),
        rotation,
        translation,
    )
    return flow.astype(np.float32), intrinsics1, intrinsics2, rotation, translation


@pytest.mark.parametrize(
    "rotation_vector, translation",
    [([0.0, 0.03, 0.01], [0.3, 0.05, 0.1]), ([0.02, -0.01, 0.0], [-0.1, 0.2, 0.3])],
)
def test_the_pose_of_exact_flow_is_the_true_motion(rotation_vector, translation):
    flow, intrinsics1, intrinsics2, rotation, translation = _pair(rotation_vector, translation)
    estimated_rotation, estimated_translation, succeeded = flow_pose.pose_of_example(
        flow, intrinsics1, intrinsics2
    )
    assert succeeded
    assert estimated_rotation.dtype == np.float32 and estimated_rotation.shape == (3, 3)
    assert np.linalg.norm(estimated_translation) == pytest.approx(1.0, abs=1e-5)
    assert geometry.rotation_error_degrees(estimated_rotation, rotation) < 0.1
    assert geometry.translation_error_degrees(estimated_translation, translation) < 0.5


def test_a_pair_without_parallax_fails_to_the_identity_and_a_zero_translation():
    flow = np.full((HEIGHT, WIDTH, 2), 0.1, np.float32)
    intrinsics = np.array([0.9, 1.2, 0.5, 0.5], np.float32)
    rotation, translation, succeeded = flow_pose.pose_of_example(flow, intrinsics, intrinsics)
    assert not succeeded
    np.testing.assert_array_equal(rotation, np.eye(3))
    np.testing.assert_array_equal(translation, np.zeros(3))


def test_poses_in_parallel_are_the_serial_ones_in_the_pairs_order():
    motions = [
        ([0.0, 0.03, 0.01], [0.3, 0.05, 0.1]),
        ([0.02, -0.01, 0.0], [-0.1, 0.2, 0.3]),
        ([0.0, 0.0, 0.0], [0.0, 0.0, 0.0]),  # no parallax: fails
        ([-0.01, 0.02, 0.01], [0.2, -0.1, 0.05]),
        ([0.01, 0.0, -0.02], [0.0, 0.3, 0.1]),
    ]
    pairs = []
    for seed, (rotation_vector, translation) in enumerate(motions):
        flow, intrinsics1, intrinsics2, _, _ = _pair(rotation_vector, translation, seed)
        pairs.append(
            (
                flow,
                geometry.intrinsics_matrix(intrinsics1, HEIGHT, WIDTH),
                geometry.intrinsics_matrix(intrinsics2, HEIGHT, WIDTH),
            )
        )
    serial = [flow_pose.estimate_pose(*pair) for pair in pairs]
    parallel = flow_pose.in_parallel(flow_pose.estimate_pose, pairs)
    assert [succeeded for _, _, succeeded in parallel] == [True, True, False, True, True]
    for (rotation, translation, succeeded), expected in zip(parallel, serial, strict=True):
        np.testing.assert_array_equal(rotation, expected[0])
        np.testing.assert_array_equal(translation, expected[1])
        assert succeeded == expected[2]
    assert flow_pose.in_parallel(flow_pose.estimate_pose, []) == []


def test_the_pose_from_the_inliers_alone_is_the_pose_from_every_point_and_the_mask(monkeypatch):
    # A flow with a fifth of its pixels wrong: RANSAC leaves them out. recoverPose is given
    # the inliers alone; called as before (every point and the RANSAC mask) it must pick
    # the same pose and count the same inliers.
    flow, intrinsics1, intrinsics2, _, _ = _pair([0.01, 0.03, 0.0], [0.3, 0.05, 0.1], seed=5)
    rng = np.random.default_rng(5)
    wrong = rng.random(flow.shape[:2]) < 0.2
    flow[wrong] += rng.normal(0.0, 4.0, (int(wrong.sum()), 2)).astype(np.float32)
    cv2 = flow_pose.opencv()
    find_essential, recover_pose = cv2.findEssentialMat, cv2.recoverPose
    seen = {}

    def find_and_keep(points1, points2, *args, **kwargs):
        essential, mask = find_essential(points1, points2, *args, **kwargs)
        seen.update(points1=points1, points2=points2, mask=mask.copy())
        return essential, mask

    def recover_both_ways(essential, points1, points2, camera_matrix):
        given = recover_pose(essential, points1, points2, camera_matrix)
        seen["as_before"] = recover_pose(
            essential, seen["points1"], seen["points2"], camera_matrix, mask=seen["mask"].copy()
        )
        seen["given_points"] = len(points1)
        return given

    monkeypatch.setattr(cv2, "findEssentialMat", find_and_keep)
    monkeypatch.setattr(cv2, "recoverPose", recover_both_ways)
    rotation, translation, succeeded = flow_pose.estimate_pose(
        flow,
        geometry.intrinsics_matrix(intrinsics1, HEIGHT, WIDTH),
        geometry.intrinsics_matrix(intrinsics2, HEIGHT, WIDTH),
    )
    assert succeeded
    inliers = int((seen["mask"] > 0).sum())
    assert seen["given_points"] == inliers < 0.9 * len(seen["points1"])
    count, rotation_before, translation_before, _ = seen["as_before"]
    assert count >= flow_pose.DEFAULT_SETTINGS.min_inliers
    np.testing.assert_array_equal(rotation, rotation_before)
    np.testing.assert_array_equal(
        translation, translation_before[:, 0] / np.linalg.norm(translation_before)
    )


def test_the_cached_pose_is_the_computed_one_and_a_caller_cannot_change_it():
    flow, intrinsics1, intrinsics2, _, _ = _pair([0.0, 0.02, 0.0], [0.3, 0.0, 0.1], seed=3)
    flow_pose._CACHE.clear()
    first = flow_pose.pose_of_example(flow, intrinsics1, intrinsics2)
    assert len(flow_pose._CACHE) == 1
    first[0][:] = 0.0
    second = flow_pose.pose_of_example(flow, intrinsics1, intrinsics2)
    direct = flow_pose.estimate_pose(
        flow,
        geometry.intrinsics_matrix(intrinsics1, HEIGHT, WIDTH),
        geometry.intrinsics_matrix(intrinsics2, HEIGHT, WIDTH),
    )
    np.testing.assert_allclose(second[0], direct[0], atol=1e-5)
    np.testing.assert_allclose(second[1], direct[1], atol=1e-5)
    # Another flow is another entry, not the cached pose.
    other = flow_pose.pose_of_example(-flow, intrinsics1, intrinsics2)
    assert len(flow_pose._CACHE) == 2
    assert not np.allclose(other[1], second[1], atol=1e-3)


def test_a_model_given_the_flow_pose_reads_it_as_its_global_parameters():
    flow, intrinsics1, intrinsics2, _, _ = _pair([0.0, 0.03, 0.01], [0.3, 0.05, 0.1])
    rotation, translation, _ = flow_pose.pose_of_example(flow, intrinsics1, intrinsics2)
    model = model_lib.GlobalLocal(global_source="flow_pose")
    assert model.extra_inputs == ("flow_rotation", "flow_translation")
    variables = state.init_variables(model, HEIGHT, WIDTH, seed=0)
    assert "global_encoder" not in variables["params"]
    images = jnp.zeros((1, HEIGHT, WIDTH, 3))
    outputs = model.apply(
        variables,
        images,
        images,
        jnp.asarray(flow)[None],
        flow_rotation=jnp.asarray(rotation)[None],
        flow_translation=jnp.asarray(translation)[None],
    )
    np.testing.assert_allclose(
        outputs["global_params"],
        model_lib.pose_parameters(jnp.asarray(rotation)[None], jnp.asarray(translation)[None]),
        atol=1e-6,
    )
    # The true pose's keys are not what it reads.
    with pytest.raises(ValueError, match="flow_rotation="):
        model.apply(
            variables,
            images,
            images,
            jnp.asarray(flow)[None],
            rotation=jnp.asarray(rotation)[None],
            translation=jnp.asarray(translation)[None],
        )
    with pytest.raises(ValueError, match="global_dim is 4"):
        registry.check_config("global_local", {"global_source": "flow_pose", "global_dim": 4})
