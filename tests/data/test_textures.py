"""Tests of solid textures and surface detail (data/gld_scenes/textures.py)."""

import numpy as np

from data.gld_scenes import scenes, textures


def test_detail_fades_out_below_two_pixels_and_is_full_above_four():
    detail = scenes.surface_detail(np.array([0.2, 0.4, 0.6]), np.zeros(3))
    points = np.random.default_rng(0).uniform(0.0, 3.0, (2000, 3)).astype(np.float32)
    finest = min(textures.DETAIL_SPACINGS)
    coarsest = max(textures.DETAIL_SPACINGS)
    # Every octave under two pixels: no detail at all.
    blurred = detail.factor(points, np.full(len(points), coarsest / 1.9, np.float32))
    np.testing.assert_array_equal(blurred, 1.0)
    # Every octave over four pixels: the full pattern, within [1 - contrast, 1 + contrast].
    sharp = detail.factor(points, np.full(len(points), finest / 4.1, np.float32))
    assert sharp.std() > 0.1 * detail.contrast
    assert np.all(np.abs(sharp - 1.0) <= detail.contrast)
    # In between, only the coarse octaves remain: the pattern is smoother.
    coarse_only = detail.factor(points, np.full(len(points), coarsest / 8.0, np.float32))
    nearby = points + np.float32(finest / 2.0)
    assert (
        np.abs(
            detail.factor(nearby, np.full(len(points), coarsest / 8.0, np.float32)) - coarse_only
        ).mean()
        < np.abs(
            detail.factor(nearby, np.full(len(points), finest / 4.1, np.float32)) - sharp
        ).mean()
    )
