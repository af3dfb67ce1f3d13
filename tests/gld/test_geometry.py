import jax.numpy as jnp
import numpy as np
import pytest
from two_view_scene import two_view_scene

from gld import geometry


def _random_pose(rng, max_angle=0.15):
    rotation = geometry.rotation_matrix(rng.normal(size=3) * max_angle)
    translation = rng.normal(size=3) * 0.3
    return rotation, translation


def test_intrinsics_round_trip_and_pixel_centre_convention():
    intrinsics = np.array([0.89115971, 1.18821287, 0.5, 0.5])
    matrix = geometry.intrinsics_matrix(intrinsics, 192, 256)
    # The principal point at the image centre sits between pixels 127 and 128.
    np.testing.assert_allclose(matrix[0, 2], 127.5)
    np.testing.assert_allclose(matrix[1, 2], 95.5)
    np.testing.assert_allclose(geometry.normalised_intrinsics(matrix, 192, 256), intrinsics)


def test_depth_to_flow_then_triangulation_recovers_depth():
    rng = np.random.default_rng(0)
    depth = rng.uniform(1.0, 5.0, size=(12, 16))
    k1 = geometry.intrinsics_matrix(np.array([0.9, 1.2, 0.5, 0.5]), 12, 16)
    k2 = geometry.intrinsics_matrix(np.array([1.0, 1.1, 0.45, 0.55]), 12, 16)
    rotation, translation = _random_pose(rng)
    flow, z2 = geometry.depth_to_flow(depth, k1, k2, rotation, translation)
    assert np.all(z2 > 0)
    recovered = geometry.triangulate_depth(flow, k1, k2, rotation, translation)
    np.testing.assert_allclose(recovered, depth, rtol=1e-6)


def test_triangulation_is_jittable_and_batched():
    rng = np.random.default_rng(1)
    depth = rng.uniform(1.0, 5.0, size=(2, 6, 8)).astype(np.float32)
    k = np.broadcast_to(geometry.intrinsics_matrix(np.array([0.9, 1.2, 0.5, 0.5]), 6, 8), (2, 3, 3))
    rotation = np.stack([_random_pose(rng)[0] for _ in range(2)]).astype(np.float32)
    translation = np.array([[0.3, 0.0, 0.1], [-0.2, 0.1, 0.3]], np.float32)
    flow, _ = geometry.depth_to_flow(depth, k, k, rotation, translation)
    recovered = geometry.triangulate_depth(
        jnp.asarray(flow),
        jnp.asarray(k),
        jnp.asarray(k),
        jnp.asarray(rotation),
        jnp.asarray(translation),
    )
    np.testing.assert_allclose(np.asarray(recovered), depth, rtol=2e-3)


def test_zero_parallax_is_not_triangulated():
    k = geometry.intrinsics_matrix(np.array([0.9, 1.2, 0.5, 0.5]), 4, 4)
    depth = geometry.triangulate_depth(np.zeros((4, 4, 2)), k, k, np.eye(3), np.zeros(3))
    assert np.all(depth == 0)


def test_relative_pose_maps_camera1_points_to_camera2():
    rng = np.random.default_rng(2)
    (r1, t1), (r2, t2) = _random_pose(rng, 1.0), _random_pose(rng, 1.0)
    world = rng.normal(size=(5, 3))
    camera1 = world @ r1.T + t1
    camera2 = world @ r2.T + t2
    rotation, translation = geometry.relative_pose(r1, t1, r2, t2)
    np.testing.assert_allclose(camera1 @ rotation.T + translation, camera2, atol=1e-12)


def test_ground_truth_flow_marks_occlusion_and_leaving_the_image():
    height, width = 8, 10
    intrinsics = np.array([0.9, 1.2, 0.5, 0.5])
    depth1 = np.full((height, width), 2.0)
    translation = np.array([0.5, 0.0, 0.0])  # camera moves right: content flows left
    depth2 = np.full((height, width), 2.0)
    depth2[:, 5] = 1.0  # an occluder in view 2
    flow, valid = geometry.ground_truth_flow(
        depth1, depth2, intrinsics, intrinsics, np.eye(3), -translation
    )
    fx = 0.9 * width
    np.testing.assert_allclose(flow[..., 0], -fx * 0.5 / 2.0, rtol=1e-6)
    np.testing.assert_allclose(flow[..., 1], 0.0, atol=1e-6)
    landing = np.arange(width) + flow[0, :, 0]
    assert not valid[:, landing < -0.5].any()
    assert not valid[:, np.rint(landing) == 5].any()
    assert valid[:, (landing > 0) & (np.rint(landing) != 5)].all()


def test_rotation_errors():
    rotation = geometry.rotation_matrix(np.array([0.0, 0.0, np.radians(30.0)]))
    assert geometry.rotation_error_degrees(rotation, np.eye(3)) == pytest.approx(30.0)
    assert geometry.translation_error_degrees(
        np.array([1.0, 0, 0]), np.array([0, 2.0, 0])
    ) == pytest.approx(90.0)


def test_epipolar_distance_is_zero_for_the_true_pose_and_scale_free_in_t():
    rng = np.random.default_rng(0)
    height, width = 24, 32
    depth = rng.uniform(2.0, 6.0, (height, width))
    intrinsics = np.array([0.9, 1.2, 0.5, 0.5])
    camera = geometry.intrinsics_matrix(intrinsics, height, width)
    rotation = geometry.rotation_matrix(np.array([0.02, -0.05, 0.01]))
    translation = np.array([0.3, -0.1, 0.2])
    flow, _ = geometry.depth_to_flow(depth, camera, camera, rotation, translation)

    def distance(rotation, translation):
        return geometry.epipolar_distance(
            flow[None], rotation[None], translation[None], intrinsics[None], intrinsics[None]
        )

    assert np.max(distance(rotation, translation)) < 1e-5
    assert np.max(distance(rotation, -3.0 * translation)) < 1e-5
    # A wrong translation direction or rotation leaves pixels off their epipolar lines.
    assert np.mean(distance(rotation, np.array([0.1, 0.3, 0.2]))) > 0.5
    assert np.mean(distance(geometry.rotation_matrix(np.zeros(3)), translation)) > 0.5
    # jax and numpy agree.
    np.testing.assert_allclose(
        distance(rotation, np.array([0.1, 0.3, 0.2])),
        geometry.epipolar_distance(
            jnp.asarray(flow[None], jnp.float32),
            jnp.asarray(rotation[None], jnp.float32),
            jnp.asarray([[0.1, 0.3, 0.2]], jnp.float32),
            jnp.asarray(intrinsics[None], jnp.float32),
            jnp.asarray(intrinsics[None], jnp.float32),
        ),
        rtol=1e-3,
        atol=1e-4,
    )


def test_skew_is_the_cross_product():
    a, b = np.array([0.3, -1.2, 2.0]), np.array([1.5, 0.4, -0.7])
    np.testing.assert_allclose(geometry.skew(a) @ b, np.cross(a, b))


@pytest.mark.parametrize("xp", [np, jnp])
def test_the_flow_of_a_known_pose_triangulates_to_the_inverse_depth(xp):
    depth, flow, camera1, camera2, rotation, translation = two_view_scene([0.3, -0.1, 0.2])
    arrays = [xp.asarray(a) for a in (flow, camera1, camera2, rotation, translation)]
    inverse_depth, confidence = geometry.triangulate_inverse_depth(*arrays)
    np.testing.assert_allclose(inverse_depth, 1 / depth, atol=1e-4)
    np.testing.assert_allclose(confidence, 1.0)  # undamped: the parallax decides all
    # A translation twice as long gives half the inverse depth (units of 1 / ||t||).
    doubled, _ = geometry.triangulate_inverse_depth(*arrays[:4], 2 * arrays[4])
    np.testing.assert_allclose(doubled, 0.5 / depth, atol=1e-4)


def test_damping_pulls_towards_infinity_where_the_parallax_says_little():
    # Forward motion: the epipole is inside the image, where the parallax vanishes.
    depth, flow, camera1, camera2, rotation, translation = two_view_scene(
        [0.0, 0.0, 0.3], (0, 0, 0)
    )
    plain, _ = geometry.triangulate_inverse_depth(flow, camera1, camera2, rotation, translation)
    damped, confidence = geometry.triangulate_inverse_depth(
        flow, camera1, camera2, rotation, translation, damping=1.0
    )
    epipole = camera2 @ translation
    u, v = epipole[:2] / epipole[2]
    grid = geometry.pixel_grid(*depth.shape)
    distance = np.hypot(grid[..., 0] - u, grid[..., 1] - v)
    near, far = distance < 2, distance > 12
    assert near.any() and far.any()
    np.testing.assert_allclose(plain, 1 / depth, rtol=1e-6)
    assert np.all(damped[near] < 0.5 / depth[near])
    assert np.all(confidence[near] < 0.5) and np.all(confidence[far] > 0.9)
    np.testing.assert_allclose(damped[far], 1 / depth[far], rtol=0.1)
    # No parallax at all (a pure rotation): inverse depth 0, not a division by zero.
    still = geometry.triangulate_inverse_depth(
        np.zeros_like(flow), camera1, camera1, np.eye(3), np.zeros(3)
    )
    assert np.all(still[0] == 0) and np.all(still[1] == 0)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_numpy_transforms_keep_the_bits_of_numpys_einsum(dtype):
    # float32 runs as multiply-adds, float64 as the einsum: both must give the einsum's
    # bits, signed zeros and non-finite values included (rendered records depend on them).
    rng = np.random.default_rng(4)
    rotation = np.stack([geometry.rotation_matrix(rng.normal(size=3)) for _ in range(2)])
    rotation = (rotation * 3.7).astype(dtype)
    translation = rng.normal(size=(2, 3)).astype(dtype)
    points = (rng.normal(size=(2, 9, 11, 3)) * 100.0).astype(dtype)
    points[0, 0, 0] = -0.0
    points[1, 2, 3] = [np.inf, -1.0, 2.0]
    points[1, 4, 5, 1] = np.nan
    points[0, 6, 7] = 1e-40
    expected = np.einsum("...ij,...hwj->...hwi", rotation, points) + translation[:, None, None]
    moved = geometry.transform_points(points, rotation, translation)
    assert moved.dtype == dtype
    assert moved.tobytes() == expected.tobytes()
    # The einsum sums from zero: three products of -0.0 give +0.0, which the translation
    # would hide. A non-negative row and a point of -0.0 show it in the product itself.
    rotation[0, 0] = np.abs(rotation[0, 0])
    product = geometry._times(rotation, points, np)
    assert product.tobytes() == np.einsum("...ij,...hwj->...hwi", rotation, points).tobytes()
