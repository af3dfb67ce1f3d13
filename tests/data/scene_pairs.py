"""Tiny gld_scenes pairs with their scenes and cameras, shared by the renderer's tests."""

from __future__ import annotations

import functools

from data.gld_scenes import raycast, renderer, scenes

HEIGHT, WIDTH = 48, 64
SETTINGS = scenes.SceneSettings(height=HEIGHT, width=WIDTH)


@functools.cache
def rendered_pairs() -> tuple[tuple[dict, raycast.Scene, raycast.Camera, raycast.Camera], ...]:
    """Four rendered pairs (seed 7, test split): (example, scene, camera1, camera2) each.

    Rendered once per test session; treat the arrays as read-only.
    """
    result = []
    for index in range(4):
        example = renderer.render_pair(renderer.example_rng(7, "test", index), SETTINGS)
        scene, camera1, camera2, _, _, _ = scenes.sample_pair(
            renderer.example_rng(7, "test", index), SETTINGS
        )
        result.append((example, scene, camera1, camera2))
    return tuple(result)
