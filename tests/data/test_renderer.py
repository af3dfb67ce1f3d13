"""Tests of the two-view renderer (data/gld_scenes/renderer.py): exact geometry, tiny renders."""

import cv2
import numpy as np
from scene_pairs import HEIGHT, SETTINGS, WIDTH, rendered_pairs

from data.gld_scenes import raycast, renderer
from gld import geometry


def _near_occlusion_boundary(depth2: np.ndarray, landing: np.ndarray) -> np.ndarray:
    """[H, W] bool: the landing point's 3x3 neighbourhood in view 2 spans a depth jump."""
    neighbourhood_min = cv2.erode(depth2, np.ones((3, 3), np.uint8))
    neighbourhood_max = cv2.dilate(depth2, np.ones((3, 3), np.uint8))
    jump = neighbourhood_max > 1.05 * neighbourhood_min
    at_landing, _ = geometry.sample_nearest(jump, landing)
    return at_landing


def test_warping_image2_with_true_flow_reproduces_image1():
    grid = geometry.pixel_grid(HEIGHT, WIDTH)
    for example, *_ in rendered_pairs():
        image1 = example["image1"].astype(np.float32) / 255.0
        image2 = example["image2"].astype(np.float32) / 255.0
        warped, inside = geometry.sample_bilinear(image2, grid + example["gt_flow"])
        valid = example["gt_flow_valid"] & inside
        assert valid.mean() > 0.5
        warp_error = np.abs(warped - image1).mean(-1)[valid].mean()
        unwarped_error = np.abs(image2 - image1).mean(-1)[valid].mean()
        assert warp_error < 0.03
        assert warp_error < 0.3 * unwarped_error


def test_depth_flow_triangulation_round_trip():
    for example, *_ in rendered_pairs():
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


def test_view2_depth_agrees_with_transformed_view1_depth():
    for example, scene, _, camera2 in rendered_pairs():
        flow, depth_in_view2 = _reproject_view1(example)
        valid = example["gt_flow_valid"]
        # Cast view-2 rays exactly through the sub-pixel landing points.
        landing = (geometry.pixel_grid(HEIGHT, WIDTH) + flow).astype(np.float32)
        cast_depth, _ = raycast.cast(scene, camera2, HEIGHT, WIDTH, pixels=landing)
        # The nearest-pixel occlusion test cannot resolve sub-pixel occlusion boundaries:
        # disagreement is allowed only right at a depth jump of view 2.
        disagrees = valid & (np.abs(cast_depth / depth_in_view2 - 1.0) > 1e-4)
        assert disagrees.mean() < 0.01
        assert np.all(_near_occlusion_boundary(example["depth2"], landing)[disagrees])
        # The rendered view-2 depth map, looked up at the nearest pixel, agrees too.
        nearest, _ = geometry.sample_nearest(example["depth2"], landing)
        assert np.median(np.abs(nearest[valid] / depth_in_view2[valid] - 1.0)) < 0.01


def test_flow_validity_excludes_occlusions_and_out_of_view():
    occluded_total = outside_total = 0
    for example, scene, _, camera2 in rendered_pairs():
        flow, depth_in_view2 = _reproject_view1(example)
        landing = geometry.pixel_grid(HEIGHT, WIDTH) + flow
        u, v = landing[..., 0], landing[..., 1]
        outside = (u < -0.5) | (u > WIDTH - 0.5) | (v < -0.5) | (v > HEIGHT - 0.5)
        cast_depth, _ = raycast.cast(
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


def test_render_is_deterministic_per_seed_and_index():
    first = renderer.render_pair(renderer.example_rng(3, "train", 5), SETTINGS)
    again = renderer.render_pair(renderer.example_rng(3, "train", 5), SETTINGS)
    other = renderer.render_pair(renderer.example_rng(3, "train", 6), SETTINGS)
    other_split = renderer.render_pair(renderer.example_rng(3, "test", 5), SETTINGS)
    for key in first:
        np.testing.assert_array_equal(first[key], again[key])
    assert not np.array_equal(first["image1"], other["image1"])
    assert not np.array_equal(first["image1"], other_split["image1"])
