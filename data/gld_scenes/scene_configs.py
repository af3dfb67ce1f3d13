"""The `gld_scenes` configurations: sizes, intrinsics, surface detail, release history.

`SceneConfig` is a TFDS builder config: `all_configs()` gives the builder's nine
(`tiny`, `small`, `full`, each also `_varying` and `_untextured`), and
`RELEASE_NOTES` / `VARYING_RELEASE` their versions' history.
"""

from __future__ import annotations

import dataclasses

import tensorflow_datasets as tfds

from gld import flow as flow_lib

from . import scenes


@dataclasses.dataclass(eq=False)
class SceneConfig(tfds.core.BuilderConfig):
    """A `gld_scenes` configuration.

    Attributes:
      height, width: image size in pixels.
      num_train, num_test: number of pairs per split.
      seed: seed of the whole dataset (with the split and the index).
      intrinsics_jitter: relative perturbation of each view's fx, fy, cx, cy (0 = nominal).
      surface_detail: detail on every surface (`scenes.SceneSettings.surface_detail`).
      flow_estimator: the stored estimated flow's estimator (`gld.flow.check_estimator`);
        a build may override it (`Builder(flow_estimator=...)`).
    """

    height: int = 192
    width: int = 256
    num_train: int = 40_000
    num_test: int = 1_000
    seed: int = 0
    intrinsics_jitter: float = 0.0
    surface_detail: bool = True
    flow_estimator: str = flow_lib.DEFAULT_ESTIMATOR

    def scene_settings(self) -> scenes.SceneSettings:
        return scenes.SceneSettings(
            height=self.height,
            width=self.width,
            intrinsics_jitter=self.intrinsics_jitter,
            surface_detail=self.surface_detail,
        )


_DETAIL_NOTE = (
    "Every surface carries band-limited multi-octave value noise fixed to it (object "
    "coordinates for objects, world coordinates for the room) that multiplies its albedo, "
    "each octave fading out between 4 and 2 pixels on the surface: the estimated flow is "
    "right where 1.0.0's large plain, gradient and striped surfaces left it wrong. "
    "Geometry, poses, depth and true flow are those of the previous version; the images "
    "and the estimated flow change. The *_untextured configs render the previous look."
)
RELEASE_NOTES = {"2.0.0": _DETAIL_NOTE, "1.0.0": "Initial release."}
# The varying configs' own history: their pairs changed when the intrinsics got a
# random stream of their own (the fixed configs' pairs did not).
VARYING_RELEASE = dict(
    version=tfds.core.Version("2.0.0"),
    release_notes={
        "2.0.0": _DETAIL_NOTE,
        "1.2.0": "Each pair is the fixed config's pair of the same index (scene, cameras' "
        "poses) with other intrinsics: the motion is bounded with the nominal intrinsics.",
        "1.1.0": "Each pair has the scene and the motion draws of the fixed config's pair "
        "of the same index.",
        "1.0.0": "Initial release.",
    },
)


def all_configs() -> list[SceneConfig]:
    """Every config of the builder: each size fixed, `_varying` and `_untextured`."""
    sizes = {
        "tiny": dict(height=48, width=64, num_train=32, num_test=16),
        "small": dict(height=96, width=128, num_train=2_000, num_test=200),
        "full": dict(height=192, width=256, num_train=40_000, num_test=1_000),
    }
    descriptions = {
        "tiny": "64x48, 32 train / 16 test pairs (tests).",
        "small": "128x96, 2,000 train / 200 test pairs (the default of the trainer).",
        "full": "256x192, 40,000 train / 1,000 test pairs (paper scale).",
    }
    configs = []
    for jitter, detail, suffix, extra in (
        (0.0, True, "", ""),
        (
            0.2,
            True,
            "_varying",
            " Varying intrinsics (20%); each pair is the fixed config's pair of the same "
            "index (scene, poses) seen with other intrinsics.",
        ),
        (
            0.0,
            False,
            "_untextured",
            " Without surface detail: the fixed config's pairs as version 1.0.0 rendered "
            "them (images and estimated flow alike), with large plain surfaces where the "
            "estimated flow is wrong.",
        ),
    ):
        for name, size in sizes.items():
            configs.append(
                SceneConfig(
                    name=name + suffix,
                    description=descriptions[name] + extra,
                    intrinsics_jitter=jitter,
                    surface_detail=detail,
                    **(VARYING_RELEASE if jitter else {}),
                    **size,
                )
            )
    return configs
