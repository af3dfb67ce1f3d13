"""What every export shares (gld/inference/export_interface.py): the formulation of a
platform and batch."""

import pytest

from gld.inference import export_interface


def test_the_formulation_follows_the_platform():
    assert export_interface.choose_formulation(None, ("cpu",), None) == "fused_aligned"
    assert export_interface.choose_formulation(None, ("cpu", "cuda"), None) == "fused_aligned"
    # The GPU default (a grouped conv) needs a static batch; a symbolic one gets "shifted".
    assert export_interface.choose_formulation(None, ("cuda",), 4) == "vmap"
    assert export_interface.choose_formulation(None, ("cuda",), None) == "shifted"
    assert export_interface.choose_formulation("map_conv", ("cuda",), None) == "map_conv"
    with pytest.raises(ValueError, match="'vmap' needs a fixed batch size"):
        export_interface.choose_formulation("vmap", ("cpu",), None)
    with pytest.raises(ValueError, match="unknown formulation 'nope'"):
        export_interface.choose_formulation("nope", ("cpu",), None)
