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


def test_the_pose_is_opencvs_recover_pose_on_every_point_and_the_ransac_mask(monkeypatch):
    # A flow with a fifth of its pixels wrong: RANSAC leaves them out. estimate_pose gives
    # recover_pose the inliers alone; OpenCV given every point and the RANSAC mask must
    # count the same inliers in front and pick the same pose, bit for bit.
    flow, intrinsics1, intrinsics2, _, _ = _pair([0.01, 0.03, 0.0], [0.3, 0.05, 0.1], seed=5)
    rng = np.random.default_rng(5)
    wrong = rng.random(flow.shape[:2]) < 0.2
    flow[wrong] += rng.normal(0.0, 4.0, (int(wrong.sum()), 2)).astype(np.float32)
    cv2 = flow_pose.opencv()
    find_essential, recover_pose = cv2.findEssentialMat, flow_pose.recover_pose
    seen = {}

    def find_and_keep(points1, points2, *args, **kwargs):
        essential, mask = find_essential(points1, points2, *args, **kwargs)
        seen.update(essential=essential, points1=points1, points2=points2, mask=mask.copy())
        return essential, mask

    def recover_and_keep(essential, points1, points2):
        seen["recovered"] = recover_pose(essential, points1, points2)
        seen["given_points"] = len(points1)
        return seen["recovered"]

    monkeypatch.setattr(cv2, "findEssentialMat", find_and_keep)
    monkeypatch.setattr(flow_pose, "recover_pose", recover_and_keep)
    rotation, translation, succeeded = flow_pose.estimate_pose(
        flow,
        geometry.intrinsics_matrix(intrinsics1, HEIGHT, WIDTH),
        geometry.intrinsics_matrix(intrinsics2, HEIGHT, WIDTH),
    )
    assert succeeded
    inliers = int((seen["mask"] > 0).sum())
    assert seen["given_points"] == inliers < 0.9 * len(seen["points1"])
    count, rotation_cv, translation_cv, _ = cv2.recoverPose(
        seen["essential"][:3], seen["points1"], seen["points2"], np.eye(3), mask=seen["mask"]
    )
    assert seen["recovered"][0] == count >= flow_pose.DEFAULT_SETTINGS.min_inliers
    np.testing.assert_array_equal(rotation, rotation_cv)
    np.testing.assert_array_equal(
        translation, translation_cv[:, 0] / np.linalg.norm(translation_cv)
    )


def test_recover_pose_counts_and_chooses_as_opencv_for_points_behind_and_at_infinity():
    # Random motions and points, some behind the first camera, some beyond the cheirality
    # distance, with noise and outliers: the count, the rotation and the translation are
    # cv2.recoverPose's, and the cases cover the decomposition's different poses.
    cv2 = flow_pose.opencv()
    chosen = set()
    for seed in range(24):
        rng = np.random.default_rng(seed)
        rotation = geometry.rotation_matrix(rng.normal(0.0, 0.1, 3))
        translation = rng.normal(0.0, 1.0, 3)
        translation /= np.linalg.norm(translation)
        count = 400
        # In front, behind, about the cheirality distance, and beyond it.
        depth = np.concatenate(
            [
                rng.uniform(2.0, 20.0, count - 90),
                rng.uniform(-8.0, -1.0, 30),
                rng.uniform(49.0, 51.0, 30),
                rng.uniform(60, 500, 30),
            ]
        )
        rays = np.concatenate([rng.uniform(-0.6, 0.6, (count, 2)), np.ones((count, 1))], axis=1)
        points = rays * depth[:, None]
        seen = points @ rotation.T + translation
        points1 = rays[:, :2] + rng.normal(0.0, 1e-3, (count, 2))
        points2 = seen[:, :2] / seen[:, 2:] + rng.normal(0.0, 1e-3, (count, 2))
        points2[:40] = rng.uniform(-0.6, 0.6, (40, 2))  # outliers
        essential, _ = cv2.findEssentialMat(
            points1, points2, np.eye(3), method=cv2.RANSAC, prob=0.999, threshold=3e-3
        )
        expected = cv2.recoverPose(essential[:3], points1, points2, np.eye(3))
        good, rotation_found, translation_found = flow_pose.recover_pose(
            essential[:3], points1, points2
        )
        assert good == expected[0]
        np.testing.assert_array_equal(rotation_found, expected[1])
        np.testing.assert_array_equal(translation_found, expected[2][:, 0])
        rotation1, _, translation1 = cv2.decomposeEssentialMat(essential[:3])
        chosen.add(
            (
                np.array_equal(rotation_found, rotation1),
                np.array_equal(translation_found, translation1[:, 0]),
            )
        )
    assert len(chosen) >= 3


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


def test_recover_pose_breaks_a_tie_between_two_poses_as_opencv():
    # Exact correspondences made in front of both cameras for one of the essential matrix's
    # four poses lie behind a camera for the other three. Ten made for each of two poses
    # tie them; OpenCV keeps the first in its order, and so must recover_pose.
    cv2 = flow_pose.opencv()
    rng = np.random.default_rng(3)
    rotation = geometry.rotation_matrix(np.array([0.05, -0.1, 0.02]))
    translation = np.array([0.6, -0.2, 0.4])
    essential = geometry.skew(translation) @ rotation
    rotation1, rotation2, unit = cv2.decomposeEssentialMat(essential)
    poses = [
        (rotation1, unit[:, 0]),
        (rotation2, unit[:, 0]),
        (rotation1, -unit[:, 0]),
        (rotation2, -unit[:, 0]),
    ]

    def made_for(pose, count=10):
        pose_rotation, pose_translation = pose
        points1, points2 = [], []
        while len(points1) < count:
            point = np.append(rng.uniform(-0.5, 0.5, 2), 1.0) * rng.uniform(2.0, 10.0)
            seen = pose_rotation @ point + pose_translation
            if seen[2] > 0:
                points1.append(point[:2] / point[2])
                points2.append(seen[:2] / seen[2])
        return np.array(points1), np.array(points2)

    made = [made_for(pose) for pose in poses]
    for first in range(4):
        for second in range(first + 1, 4):
            points1 = np.concatenate([made[first][0], made[second][0]])
            points2 = np.concatenate([made[first][1], made[second][1]])
            expected = cv2.recoverPose(essential, points1, points2, np.eye(3))
            good, rotation_found, translation_found = flow_pose.recover_pose(
                essential, points1, points2
            )
            assert good == expected[0] == 10
            np.testing.assert_array_equal(rotation_found, poses[first][0])
            np.testing.assert_array_equal(translation_found, poses[first][1])
            np.testing.assert_array_equal(rotation_found, expected[1])
            np.testing.assert_array_equal(translation_found, expected[2][:, 0])
