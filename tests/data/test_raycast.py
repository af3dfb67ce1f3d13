"""Tests of ray casting (data/gld_scenes/raycast.py) on hand-made scenes and tiny renders."""

import dataclasses

import numpy as np
import pytest
from scene_pairs import HEIGHT, WIDTH, rendered_pairs

from data.gld_scenes import raycast, scenes, shapes, textures
from gld import geometry


def _plain(color=(0.5, 0.5, 0.5)) -> textures.Material:
    return textures.Material(
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
    return shapes.SceneObject(
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


def _detailed(material: textures.Material) -> textures.Material:
    return dataclasses.replace(
        material, detail=scenes.surface_detail(material.color_a, np.array([1.0, 2.0, 3.0]))
    )


def test_detail_moves_with_its_object_and_stays_with_the_room():
    # The same scene moved by an offset (object, camera, light): the object's pixels are the
    # same (its detail is fixed to the object), the room's are not (its detail is fixed to
    # the world, which did not move).
    camera_center = np.array([3.0, 1.5, 2.0])
    offset = np.array([0.37, 0.11, 0.23])
    room_materials = tuple(_detailed(_plain((0.5, 0.6, 0.4))) for _ in range(6))
    obj = dataclasses.replace(
        _shape("box", camera_center + [0.0, 0.0, 3.0], [0.8, 0.6, 0.5]),
        material=_detailed(_plain((0.7, 0.3, 0.2))),
    )

    def render(shift):
        scene = dataclasses.replace(
            _room_with([dataclasses.replace(obj, center=obj.center + shift)]),
            room_materials=room_materials,
            light_position=np.array([3.0, 2.9, 5.0], np.float32) + shift,
        )
        image, _, surface = raycast.render_view(
            scene, _forward_camera(camera_center + shift), 49, 65
        )
        return image.astype(np.float32), surface

    image, surface = render(np.zeros(3))
    moved, moved_surface = render(offset)
    on_object = surface == raycast.ROOM_SURFACES
    np.testing.assert_array_equal(on_object, moved_surface == raycast.ROOM_SURFACES)
    assert on_object.mean() > 0.2 and (~on_object).mean() > 0.2
    assert image[on_object].std() > 5.0  # the plain box has a pattern
    assert np.abs(moved - image)[on_object].max() <= 1.0  # rounding only
    assert np.abs(moved - image)[~on_object].mean() > 5.0


def test_surface_detail_adds_nothing_to_the_scene_draws():
    settings = scenes.SceneSettings(height=HEIGHT, width=WIDTH)
    plain = dataclasses.replace(settings, surface_detail=False)
    detailed_pair = scenes.sample_pair(np.random.default_rng(3), settings)
    plain_pair = scenes.sample_pair(np.random.default_rng(3), plain)
    (scene, camera1, camera2, image1, depth1, surface1) = detailed_pair
    (scene_p, camera1_p, camera2_p, image1_p, depth1_p, surface1_p) = plain_pair
    np.testing.assert_array_equal(depth1, depth1_p)
    np.testing.assert_array_equal(surface1, surface1_p)
    np.testing.assert_array_equal(camera2.rotation, camera2_p.rotation)
    np.testing.assert_array_equal(camera2.translation, camera2_p.translation)
    assert all(m.detail is not None for m in scene.room_materials)
    assert all(m.detail is None for m in scene_p.room_materials)
    assert not np.array_equal(image1, image1_p)


def test_texture_kinds_name_each_pixels_material():
    for example, scene, camera1, _ in rendered_pairs():
        _, _, surface = raycast.render_view(scene, camera1, HEIGHT, WIDTH)
        kinds = raycast.texture_kinds(scene, surface)
        np.testing.assert_array_equal(kinds, example["texture_kind1"])
        materials = scene.room_materials + tuple(obj.material for obj in scene.objects)
        row, col = np.unravel_index(np.argmax(surface), surface.shape)
        assert textures.TEXTURES[kinds[row, col]] == materials[surface[row, col]].kind
