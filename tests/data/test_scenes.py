"""Tests of scene and camera-motion sampling (data/gld_scenes/scenes.py), tiny renders."""

import dataclasses

import numpy as np
import pytest
from scene_pairs import HEIGHT, SETTINGS, WIDTH, rendered_pairs

from data.gld_scenes import raycast, renderer, scenes
from gld import geometry


def test_scene_content_and_flow_range():
    for example, scene, camera1, _ in rendered_pairs():
        assert np.all(example["depth1"] > 0) and np.all(example["depth2"] > 0)
        center = camera1.center
        assert np.all(center > 0) and np.all(center < scene.room_size)
        _, surface = raycast.cast(scene, camera1, HEIGHT, WIDTH)
        assert (surface >= raycast.ROOM_SURFACES).mean() > 0.05  # objects are in view
        magnitude = np.linalg.norm(example["gt_flow"], axis=-1)[example["gt_flow_valid"]]
        max_flow = SETTINGS.max_flow_fraction * WIDTH
        assert np.percentile(magnitude, 99) <= 1.05 * max_flow
        translation_norm = np.linalg.norm(example["translation"])
        assert 0.05 - 1e-6 <= translation_norm <= 0.5 + 1e-6
        assert geometry.rotation_angle_degrees(example["rotation"]) <= 10.0 + 1e-3


def test_varying_intrinsics_differ_between_views_within_20_percent():
    varying = dataclasses.replace(SETTINGS, intrinsics_jitter=0.2)
    nominal = np.asarray(scenes.NOMINAL_INTRINSICS, np.float32)
    for index in range(3):
        example = renderer.render_pair(renderer.example_rng(0, "train", index), varying)
        intrinsics1, intrinsics2 = example["intrinsics1"], example["intrinsics2"]
        assert np.all(np.abs(intrinsics1 - intrinsics2) > 0)
        for intrinsics in (intrinsics1, intrinsics2):
            assert np.all(np.abs(intrinsics / nominal - 1.0) <= 0.2 + 1e-6)
    fixed = renderer.render_pair(renderer.example_rng(0, "train", 0), SETTINGS)
    np.testing.assert_array_equal(fixed["intrinsics1"], nominal)
    np.testing.assert_array_equal(fixed["intrinsics2"], nominal)


def test_varying_intrinsics_keep_the_scene_and_the_motion_of_the_nominal_pair():
    nominal = SETTINGS
    varying = dataclasses.replace(nominal, intrinsics_jitter=0.2)
    for index in range(3):
        pairs = [
            scenes.sample_pair(renderer.example_rng(0, "train", index), settings)
            for settings in (nominal, varying)
        ]
        (scene, camera1, camera2, *_), (scene_v, camera1_v, camera2_v, *_) = pairs
        assert scene.room_size.tolist() == scene_v.room_size.tolist()
        assert [o.center.tolist() for o in scene.objects] == [
            o.center.tolist() for o in scene_v.objects
        ]
        for a, b in ((camera1, camera1_v), (camera2, camera2_v)):
            np.testing.assert_allclose(a.rotation, b.rotation, atol=1e-12)
            np.testing.assert_allclose(a.translation, b.translation, atol=1e-12)
        assert not np.allclose(camera1.intrinsics, camera1_v.intrinsics)


def test_bad_settings_raise():
    with pytest.raises(ValueError, match="intrinsics_jitter"):
        scenes.SceneSettings(intrinsics_jitter=1.5)
    with pytest.raises(ValueError, match="image size"):
        scenes.SceneSettings(height=2, width=64)
