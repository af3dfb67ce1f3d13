"""A built gld_scenes example's view 1 drawn again from its seed, as the builder draws it
(an example is a pure function of its config's seed, split and index): what a pixel
shows that the records do not store, its surface's texture kind
(`python -m experiments.regimes`)."""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from typing import Any

import numpy as np

from . import raycast, renderer, scenes, textures


def texture_reader(
    builder,
) -> Callable[[Mapping[str, Any]], tuple[np.ndarray, Sequence[str]]] | None:
    """For a gld_scenes builder: decoded example -> (the texture kind [H, W] int8 of each
    pixel of view 1, an index into the names; the names, `textures.TEXTURES`); None for
    other datasets.

    The reader raises ValueError when the scene drawn again does not give the record's
    depth: the dataset was built by other code than this one."""
    if not builder.name.startswith("gld_scenes"):
        return None
    config = builder.builder_config
    settings = config.scene_settings()

    def read(example: Mapping[str, Any]) -> tuple[np.ndarray, Sequence[str]]:
        _, _, split, index = example["id"].split("/")
        rng = renderer.example_rng(config.seed, split, int(index))
        # `renderer.render_pair` draws view 1 with this call before anything else.
        scene, _, _, _, depth1, surface1 = scenes.sample_pair(rng, settings)
        stored = example["depth"]
        if not np.array_equal(np.where(example["depth_valid"], depth1, 0.0), stored):
            raise ValueError(
                f"{example['id']}: the scene drawn again from its seed does not give the "
                "record's depth; the dataset was built by other code than this one"
            )
        return raycast.texture_kinds(scene, surface1), textures.TEXTURES

    return read
