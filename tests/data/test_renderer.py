"""Tests of the procedural two-view renderer (data/gld_scenes/renderer.py), tiny renders."""

import dataclasses

import cv2
import numpy as np
import pytest

from data.gld_scenes import renderer
from gld import geometry

HEIGHT, WIDTH = 48, 64
SETTINGS = renderer.SceneSettings(height=HEIGHT, width=WIDTH)


@pytest.fixture(scope="module")
def pairs():
    """A few rendered pairs with their scenes and cameras."""
    result = []
    for index in range(4):
        example = renderer.render_pair(renderer.example_rng(7, "test", index), SETTINGS)
        scene, camera1, camera2, _, _ = renderer.sample_pair(
            renderer.example_rng(7, "test", index), SETTINGS
        )
        result.append((example, scene, camera1, camera2))
    return result


def _near_occlusion_boundary(depth2: np.ndarray, landing: np.ndarray) -> np.ndarray:
    """[H, W] bool: the landing point's 3x3 neighbourhood in view 2 spans a depth jump."""
    neighbourhood_min = cv2.erode(depth2, np.ones((3, 3), np.uint8))
    neighbourhood_max = cv2.dilate(depth2, np.ones((3, 3), np.uint8))
    jump = neighbourhood_max > 1.05 * neighbourhood_min
    at_landing, _ = geometry.sample_nearest(jump, landing)
    return at_landing


def _plain(color=(0.5, 0.5, 0.5)) -> renderer.Material:
    return renderer.Material(
        kind="plain",
        color_a=np.asarray(color, np.float32),
        color_b=np.asarray(color, np.float32),
        scale=1.0,
        direction=np.array([1.0, 0.0, 0.0], np.float32),
        offset=np.zeros(3, np.float32),
    )


def _room_with(objects) -> renderer.Scene:
    return renderer.Scene(
        room_size=np.array([6.0, 3.0, 10.0], np.float32),
        room_materials=tuple(_plain() for _ in range(6)),
        objects=tuple(objects),
        light_position=np.array([3.0, 2.9, 5.0], np.float32),
        ambient=0.3,
    )


def _forward_camera(center, intrinsics=renderer.NOMINAL_INTRINSICS) -> renderer.Camera:
    """A camera at `center` looking along world +z (camera y = world -y)."""
    rotation = renderer.look_at_rotation(np.array([0.0, 0.0, 1.0]), 0.0)
    center = np.asarray(center, np.float64)
    return renderer.Camera(rotation, -rotation @ center, np.asarray(intrinsics))


def _shape(shape, center, size):
    return renderer.SceneObject(
        shape=shape,
        center=np.asarray(center, np.float32),
        rotation=np.eye(3, dtype=np.float32),
        size=np.asarray(size, np.float32),
        material=_plain((0.9, 0.1, 0.1)),
    )


@pytest.mark.parametrize(
    "shape, size, front_distance",
    [("sphere", [0.5], 0.5), ("box", [0.3, 0.4, 0.6], 0.6), ("cylinder", [0.4, 0.5], 0.4)],
)
def test_ray_hits_known_distance(shape, size, front_distance):
    # Camera at the room's mid-height; the object 4 m ahead on the optical axis. An odd
    # image size puts a pixel exactly on the principal point.
    center = np.array([3.0, 1.5, 2.0])
    obj = _shape(shape, center + [0.0, 0.0, 4.0], size)
    camera = _forward_camera(center)
    depth, surface = renderer.cast(_room_with([obj]), camera, 49, 65)
    assert surface[24, 32] == renderer.ROOM_SURFACES
    np.testing.assert_allclose(depth[24, 32], 4.0 - front_distance, rtol=1e-5)
    # Corner pixels see the room; its far wall is 8 m ahead (camera-z depth).
    assert surface[0, 0] < renderer.ROOM_SURFACES
    assert depth.max() <= 8.0 + 1e-4


def test_room_depth_is_camera_z_of_far_wall():
    center = np.array([3.0, 1.5, 2.0])
    depth, surface = renderer.cast(_room_with([]), _forward_camera(center), 49, 65)
    # The far wall (z = 10) is a plane of constant camera z = 8 around the image centre.
    assert surface[24, 32] == 5
    np.testing.assert_allclose(depth[20:29, 28:37], 8.0, rtol=1e-5)


def test_screen_culling_matches_brute_force(pairs):
    for _, scene, camera1, _ in pairs:
        culled_depth, culled_surface = renderer.cast(scene, camera1, HEIGHT, WIDTH)
        grid = geometry.pixel_grid(HEIGHT, WIDTH)
        depth, surface = renderer.cast(scene, camera1, HEIGHT, WIDTH, pixels=grid)
        np.testing.assert_array_equal(culled_surface, surface)
        np.testing.assert_allclose(culled_depth, depth, rtol=1e-6)


def test_warping_image2_with_true_flow_reproduces_image1(pairs):
    grid = geometry.pixel_grid(HEIGHT, WIDTH)
    for example, *_ in pairs:
        image1 = example["image1"].astype(np.float32) / 255.0
        image2 = example["image2"].astype(np.float32) / 255.0
        warped, inside = geometry.sample_bilinear(image2, grid + example["gt_flow"])
        valid = example["gt_flow_valid"] & inside
        assert valid.mean() > 0.5
        warp_error = np.abs(warped - image1).mean(-1)[valid].mean()
        unwarped_error = np.abs(image2 - image1).mean(-1)[valid].mean()
        assert warp_error < 0.03
        assert warp_error < 0.3 * unwarped_error


def test_depth_flow_triangulation_round_trip(pairs):
    for example, *_ in pairs:
        camera_matrix1 = geometry.intrinsics_matrix(example["intrinsics1"], HEIGHT, WIDTH)
        camera_matrix2 = geometry.intrinsics_matrix(example["intrinsics2"], HEIGHT, WIDTH)
        rotation, translation = example["rotation"], example["translation"]
        flow, _ = geometry.depth_to_flow(
            example["depth1"], camera_matrix1, camera_matrix2, rotation, translation
        )
        np.testing.assert_allclose(
            flow[example["gt_flow_valid"]], example["gt_flow"][example["gt_flow_valid"]], atol=1e-3
        )
        depth = geometry.triangulate_depth(
            example["gt_flow"], camera_matrix1, camera_matrix2, rotation, translation
        )
        # Only pixels with parallax are triangulable: the flow must differ from the flow
        # of a point at infinity (rotation only) by more than a pixel.
        infinity_flow, _ = geometry.depth_to_flow(
            np.full((HEIGHT, WIDTH), 1e9), camera_matrix1, camera_matrix2, rotation, 0 * translation
        )
        parallax = np.linalg.norm(example["gt_flow"] - infinity_flow, axis=-1)
        usable = example["gt_flow_valid"] & (parallax > 1.0)
        assert usable.mean() > 0.3
        relative_error = np.abs(depth - example["depth1"]) / example["depth1"]
        assert relative_error[usable].max() < 1e-3


def _reproject_view1(example):
    """Flow and view-2 depth of every view-1 pixel, in float64, from the record's depth,
    intrinsics and pose."""
    return geometry.depth_to_flow(
        example["depth1"].astype(np.float64),
        geometry.intrinsics_matrix(example["intrinsics1"], HEIGHT, WIDTH),
        geometry.intrinsics_matrix(example["intrinsics2"], HEIGHT, WIDTH),
        example["rotation"].astype(np.float64),
        example["translation"].astype(np.float64),
    )


def test_view2_depth_agrees_with_transformed_view1_depth(pairs):
    for example, scene, _, camera2 in pairs:
        flow, depth_in_view2 = _reproject_view1(example)
        valid = example["gt_flow_valid"]
        # Cast view-2 rays exactly through the sub-pixel landing points.
        landing = (geometry.pixel_grid(HEIGHT, WIDTH) + flow).astype(np.float32)
        cast_depth, _ = renderer.cast(scene, camera2, HEIGHT, WIDTH, pixels=landing)
        # The nearest-pixel occlusion test cannot resolve sub-pixel occlusion boundaries:
        # disagreement is allowed only right at a depth jump of view 2.
        disagrees = valid & (np.abs(cast_depth / depth_in_view2 - 1.0) > 1e-4)
        assert disagrees.mean() < 0.01
        assert np.all(_near_occlusion_boundary(example["depth2"], landing)[disagrees])
        # The rendered view-2 depth map, looked up at the nearest pixel, agrees too.
        nearest, _ = geometry.sample_nearest(example["depth2"], landing)
        assert np.median(np.abs(nearest[valid] / depth_in_view2[valid] - 1.0)) < 0.01


def test_flow_validity_excludes_occlusions_and_out_of_view(pairs):
    occluded_total = outside_total = 0
    for example, scene, _, camera2 in pairs:
        flow, depth_in_view2 = _reproject_view1(example)
        landing = geometry.pixel_grid(HEIGHT, WIDTH) + flow
        u, v = landing[..., 0], landing[..., 1]
        outside = (u < -0.5) | (u > WIDTH - 0.5) | (v < -0.5) | (v > HEIGHT - 0.5)
        cast_depth, _ = renderer.cast(
            scene, camera2, HEIGHT, WIDTH, pixels=landing.astype(np.float32)
        )
        # Occluded: something is clearly nearer to camera 2 along the landing ray.
        occluded = ~outside & (cast_depth < 0.9 * depth_in_view2)
        valid = example["gt_flow_valid"]
        assert not np.any(valid & outside)
        # Only at sub-pixel occlusion boundaries may an occluded pixel pass the test.
        missed = valid & occluded
        assert missed.mean() < 0.01
        assert np.all(_near_occlusion_boundary(example["depth2"], landing)[missed])
        occluded_total += occluded.sum()
        outside_total += outside.sum()
    assert occluded_total > 0 and outside_total > 0


def test_scene_content_and_flow_range(pairs):
    for example, scene, camera1, _ in pairs:
        assert np.all(example["depth1"] > 0) and np.all(example["depth2"] > 0)
        center = camera1.center
        assert np.all(center > 0) and np.all(center < scene.room_size)
        _, surface = renderer.cast(scene, camera1, HEIGHT, WIDTH)
        assert (surface >= renderer.ROOM_SURFACES).mean() > 0.05  # objects are in view
        magnitude = np.linalg.norm(example["gt_flow"], axis=-1)[example["gt_flow_valid"]]
        max_flow = SETTINGS.max_flow_fraction * WIDTH
        assert np.percentile(magnitude, 99) <= 1.05 * max_flow
        translation_norm = np.linalg.norm(example["translation"])
        assert 0.05 - 1e-6 <= translation_norm <= 0.5 + 1e-6
        assert geometry.rotation_angle_degrees(example["rotation"]) <= 10.0 + 1e-3


def test_render_is_deterministic_per_seed_and_index():
    first = renderer.render_pair(renderer.example_rng(3, "train", 5), SETTINGS)
    again = renderer.render_pair(renderer.example_rng(3, "train", 5), SETTINGS)
    other = renderer.render_pair(renderer.example_rng(3, "train", 6), SETTINGS)
    other_split = renderer.render_pair(renderer.example_rng(3, "test", 5), SETTINGS)
    for key in first:
        np.testing.assert_array_equal(first[key], again[key])
    assert not np.array_equal(first["image1"], other["image1"])
    assert not np.array_equal(first["image1"], other_split["image1"])


def test_varying_intrinsics_differ_between_views_within_20_percent():
    varying = dataclasses.replace(SETTINGS, intrinsics_jitter=0.2)
    nominal = np.asarray(renderer.NOMINAL_INTRINSICS, np.float32)
    for index in range(3):
        example = renderer.render_pair(renderer.example_rng(0, "train", index), varying)
        intrinsics1, intrinsics2 = example["intrinsics1"], example["intrinsics2"]
        assert np.all(np.abs(intrinsics1 - intrinsics2) > 0)
        for intrinsics in (intrinsics1, intrinsics2):
            assert np.all(np.abs(intrinsics / nominal - 1.0) <= 0.2 + 1e-6)
    fixed = renderer.render_pair(renderer.example_rng(0, "train", 0), SETTINGS)
    np.testing.assert_array_equal(fixed["intrinsics1"], nominal)
    np.testing.assert_array_equal(fixed["intrinsics2"], nominal)


def test_bad_settings_raise():
    with pytest.raises(ValueError, match="intrinsics_jitter"):
        renderer.SceneSettings(intrinsics_jitter=1.5)
    with pytest.raises(ValueError, match="image size"):
        renderer.SceneSettings(height=2, width=64)
