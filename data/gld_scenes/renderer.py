"""One two-view example of `gld_scenes`: its random generator and its render.

`render_pair` draws a scene and two cameras (`scenes`), renders both views
(`raycast`) and derives the exact relative pose and flow; `example_rng` seeds it
from (dataset seed, split, index), so an example is a pure function of those three.

Poses follow `gld.geometry`: world-to-camera `X_cam = R X_world + t`, and the
relative pose is `X2 = R X1 + t`.
"""

from __future__ import annotations

import zlib
from typing import Any

import numpy as np

from gld import geometry

from . import raycast, scenes

# `render_pair`'s settings, named here too: callers build them as `renderer.SceneSettings`.
from .scenes import SceneSettings


def example_rng(seed: int, split: str, index: int) -> np.random.Generator:
    """The generator of example `index` of `split`: independent of build order and workers."""
    split_code = zlib.crc32(split.encode())
    return np.random.default_rng(np.random.SeedSequence([int(seed), split_code, int(index)]))


def render_pair(rng: np.random.Generator, settings: SceneSettings) -> dict[str, Any]:
    """One two-view example with exact geometry.

    Returns:
      A dict with image1, image2 [H, W, 3] uint8; depth1, depth2 [H, W] float32
      camera-z metres; intrinsics1, intrinsics2 [4] float32 normalised; rotation
      [3, 3], translation [3] float32 (X2 = R X1 + t, metres); gt_flow [H, W, 2]
      float32 pixels I1 -> I2 and gt_flow_valid [H, W] bool (lands inside view 2,
      in front of it and not occluded there); texture_kind1 [H, W] int8, the texture
      kind of view 1's surface at each pixel (an index into `textures.TEXTURES`; not
      stored in the records).
    """
    scene, camera1, camera2, image1, depth1, surface1 = scenes.sample_pair(rng, settings)
    image2, depth2, _ = raycast.render_view(scene, camera2, settings.height, settings.width)
    rotation, translation = geometry.relative_pose(
        camera1.rotation, camera1.translation, camera2.rotation, camera2.translation
    )
    gt_flow, gt_flow_valid = geometry.ground_truth_flow(
        depth1, depth2, camera1.intrinsics, camera2.intrinsics, rotation, translation
    )
    return {
        "image1": image1,
        "image2": image2,
        "depth1": depth1,
        "depth2": depth2,
        "intrinsics1": np.asarray(camera1.intrinsics, np.float32),
        "intrinsics2": np.asarray(camera2.intrinsics, np.float32),
        "rotation": np.asarray(rotation, np.float32),
        "translation": np.asarray(translation, np.float32),
        "gt_flow": gt_flow,
        "gt_flow_valid": gt_flow_valid,
        "texture_kind1": raycast.texture_kinds(scene, surface1),
    }
