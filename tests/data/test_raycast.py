"""Tests of ray casting (data/gld_scenes/raycast.py) on hand-made scenes and tiny renders."""

import numpy as np
import pytest
from scene_pairs import HEIGHT, WIDTH, rendered_pairs

from data.gld_scenes import raycast, scenes
from gld import geometry


def _plain(color=(0.5, 0.5, 0.5)) -> raycast.Material:
    return raycast.Material(
        kind="plain",
        color_a=np.asarray(color, np.float32),
        color_b=np.asarray(color, np.float32),
        scale=1.0,
        direction=np.array([1.0, 0.0, 0.0], np.float32),
        offset=np.zeros(3, np.float32),
    )


def _room_with(objects) -> raycast.Scene:
    return raycast.Scene(
        room_size=np.array([6.0, 3.0, 10.0], np.float32),
        room_materials=tuple(_plain() for _ in range(6)),
        objects=tuple(objects),
        light_position=np.array([3.0, 2.9, 5.0], np.float32),
        ambient=0.3,
    )


def _forward_camera(center, intrinsics=scenes.NOMINAL_INTRINSICS) -> raycast.Camera:
    """A camera at `center` looking along world +z (camera y = world -y)."""
    rotation = scenes.look_at_rotation(np.array([0.0, 0.0, 1.0]), 0.0)
    center = np.asarray(center, np.float64)
    return raycast.Camera(rotation, -rotation @ center, np.asarray(intrinsics))


def _shape(shape, center, size):
    return raycast.SceneObject(
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
    depth, surface = raycast.cast(_room_with([obj]), camera, 49, 65)
    assert surface[24, 32] == raycast.ROOM_SURFACES
    np.testing.assert_allclose(depth[24, 32], 4.0 - front_distance, rtol=1e-5)
    # Corner pixels see the room; its far wall is 8 m ahead (camera-z depth).
    assert surface[0, 0] < raycast.ROOM_SURFACES
    assert depth.max() <= 8.0 + 1e-4


def test_room_depth_is_camera_z_of_far_wall():
    center = np.array([3.0, 1.5, 2.0])
    depth, surface = raycast.cast(_room_with([]), _forward_camera(center), 49, 65)
    # The far wall (z = 10) is a plane of constant camera z = 8 around the image centre.
    assert surface[24, 32] == 5
    np.testing.assert_allclose(depth[20:29, 28:37], 8.0, rtol=1e-5)


def test_screen_culling_matches_brute_force():
    for _, scene, camera1, _ in rendered_pairs():
        culled_depth, culled_surface = raycast.cast(scene, camera1, HEIGHT, WIDTH)
        grid = geometry.pixel_grid(HEIGHT, WIDTH)
        depth, surface = raycast.cast(scene, camera1, HEIGHT, WIDTH, pixels=grid)
        np.testing.assert_array_equal(culled_surface, surface)
        np.testing.assert_allclose(culled_depth, depth, rtol=1e-6)
