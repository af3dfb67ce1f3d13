"""Converting a model to ONNX (gld/inference/onnx_export.py): refusals, and the converted
graph against the network written out in numpy."""

import json
import sys

import export_checks
import global_local_reference as reference
import numpy as np
import pytest
from export_checks import HEIGHT, WIDTH

from gld.inference import onnx_export


@pytest.fixture(scope="module")
def tiny_model():
    return export_checks.tiny_model()


def test_onnx_refuses_vmap_and_names_the_missing_converter(tiny_model, tmp_path, monkeypatch):
    model, variables = tiny_model
    path = tmp_path / "model.onnx"
    with pytest.raises(ValueError, match="'vmap' cannot be exported to ONNX"):
        onnx_export.export_onnx(
            model, variables, path, height=HEIGHT, width=WIDTH, batch_size=1, formulation="vmap"
        )
    monkeypatch.setitem(sys.modules, "jax2onnx", None)  # as if it were not installed
    with pytest.raises(ImportError, match="pip install jax2onnx onnxruntime"):
        onnx_export.export_onnx(model, variables, path, height=HEIGHT, width=WIDTH)
    assert not path.exists()


def test_onnx_matches_the_live_model_for_any_batch(tiny_model, tmp_path):
    pytest.importorskip("jax2onnx")
    onnx = pytest.importorskip("onnx")
    onnxruntime = pytest.importorskip("onnxruntime")
    model, variables = tiny_model
    path = tmp_path / "model.onnx"
    metadata = onnx_export.export_onnx(
        model, variables, path, height=HEIGHT, width=WIDTH, formulation="shifted"
    )
    stored = onnx.load(str(path))
    assert json.loads(stored.metadata_props[0].value) == metadata
    assert metadata["formulation"] == "shifted" and metadata["inputs"][0]["shape"][0] == "batch"
    session = onnxruntime.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    assert [entry.name for entry in session.get_inputs()] == [
        "image1",
        "image2",
        "flow",
    ]
    names = [entry.name for entry in session.get_outputs()]
    assert set(names) == {"inv_depth", "depth", "global_params"}
    for batch_size in (1, 3):
        image1, image2, flow = export_checks.model_inputs(batch_size, seed=batch_size)
        got = session.run(names, {"image1": image1, "image2": image2, "flow": flow})
        want = reference.global_local(model, variables, image1 - 0.5, image2 - 0.5, flow)
        for key, value in zip(names, got, strict=True):
            np.testing.assert_allclose(value, want[key], rtol=1e-4, atol=1e-5)
