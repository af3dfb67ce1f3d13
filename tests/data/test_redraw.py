"""A built gld_scenes example's view 1 drawn again (data/gld_scenes/redraw.py): its texture
kinds, for gld_scenes only, and refused where the scene drawn again is not the record's."""

from types import SimpleNamespace

import numpy as np
import pytest

from data.gld_scenes import redraw, textures
from gld import contract


def test_other_datasets_have_no_texture_reader():
    assert redraw.texture_reader(SimpleNamespace(name="demon")) is None


def test_the_texture_kinds_are_those_of_the_records_scene(tiny_scenes):
    read = redraw.texture_reader(tiny_scenes)
    source = tiny_scenes.as_data_source("test")
    kinds_seen = set()
    for index in range(3):
        example = contract.decode_example(source[index])
        texture_kind, names = read(example)
        assert names == textures.TEXTURES
        assert texture_kind.shape == example["depth"].shape
        assert texture_kind.min() >= 0 and texture_kind.max() < len(names)
        kinds_seen.update(np.unique(texture_kind).tolist())
    assert len(kinds_seen) > 1  # rooms and objects of several kinds
    example["depth"] = np.where(example["depth_valid"], example["depth"] * 1.01, 0.0)
    with pytest.raises(ValueError, match="does not give the record's depth"):
        read(example)
