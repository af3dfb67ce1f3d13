"""Exporting a model with jax.export (gld/inference/export.py): the file's contents,
formulations, platforms, refusals."""

import json
import zipfile

import export_checks
import global_local_reference as reference
import jax
import numpy as np
import pytest
from conftest import TINY_MODEL
from export_checks import HEIGHT, WIDTH

from gld.inference import export
from gld.models import registry


@pytest.fixture(scope="module")
def tiny_model():
    return export_checks.tiny_model()


def _read(path):
    with zipfile.ZipFile(path) as archive:
        metadata = json.loads(archive.read(export.METADATA_MEMBER))
        exported = jax.export.deserialize(bytearray(archive.read(export.EXPORTED_MEMBER)))
        with archive.open(export.WEIGHTS_MEMBER) as handle, np.load(handle) as stored:
            weights = [stored[f"{i:05d}"] for i in range(len(stored.files))]
    return metadata, exported, weights


def test_the_file_describes_the_model_and_runs_any_batch(tiny_model, tmp_path):
    model, variables = tiny_model
    path = tmp_path / "nested" / "model.gldx"
    source = {"workdir": "/runs/x", "step": 7}
    metadata = export.export_model(
        model, variables, path, height=HEIGHT, width=WIDTH, source=source
    )
    stored, exported, weights = _read(path)
    assert stored == metadata
    assert (stored["height"], stored["width"], stored["batch_size"]) == (HEIGHT, WIDTH, None)
    assert stored["model"] == "global_local" and stored["source"] == source
    assert stored["model_config"]["encoder_channels"] == TINY_MODEL["encoder_channels"]
    assert stored["formulation"] == "fused_aligned" and stored["platforms"] == ["cpu"]
    assert [entry["name"] for entry in stored["inputs"]] == ["image1", "image2", "flow"]
    assert stored["inputs"][2]["shape"] == ["batch", HEIGHT, WIDTH, 2]
    outputs = {entry["name"]: entry["shape"] for entry in stored["outputs"]}
    assert outputs == {
        "inv_depth": ["batch", HEIGHT, WIDTH],
        "depth": ["batch", HEIGHT, WIDTH],
        "global_params": ["batch", 6],
    }
    assert "baseline" in stored["depth_units"]
    # One stored array per variable, named by its path, in the order the function takes.
    leaves = jax.tree_util.tree_leaves(variables)
    assert len(weights) == len(stored["weights"]) == len(leaves)
    names = [entry["name"] for entry in stored["weights"]]
    assert "params/final_conv/kernel" in names
    for weight, leaf in zip(weights, leaves, strict=True):
        np.testing.assert_array_equal(weight, np.asarray(leaf))
    # The batch axis is symbolic: two batch sizes through the same module, each giving
    # the model's outputs (the network written out in numpy).
    assert str(exported.in_avals[-1].shape[0]) == "batch"
    for batch_size in (1, 3):
        image1, image2, flow = export_checks.model_inputs(batch_size)
        got = exported.call(weights, image1, image2, flow)
        want = reference.global_local(model, variables, image1 - 0.5, image2 - 0.5, flow)
        assert set(got) == set(outputs)
        for key in got:
            np.testing.assert_allclose(got[key], want[key], rtol=1e-4, atol=1e-6)


def test_a_fixed_batch_and_several_platforms(tiny_model, tmp_path):
    model, variables = tiny_model
    path = tmp_path / "model.gldx"
    metadata = export.export_model(
        model,
        variables,
        path,
        height=HEIGHT,
        width=WIDTH,
        platforms=("cpu", "cuda"),
        batch_size=2,
        formulation="vmap",
    )
    assert metadata["batch_size"] == 2 and metadata["formulation"] == "vmap"
    assert metadata["inputs"][0]["shape"] == [2, HEIGHT, WIDTH, 3]
    _, exported, weights = _read(path)
    assert exported.platforms == ("cpu", "cuda")
    image1, image2, flow = export_checks.model_inputs(2, seed=1)
    # The CPU lowering of the two-platform module runs here and gives the model's depth.
    np.testing.assert_allclose(
        exported.call(weights, image1, image2, flow)["inv_depth"],
        reference.global_local(model, variables, image1 - 0.5, image2 - 0.5, flow)["inv_depth"],
        rtol=1e-4,
    )
    with pytest.raises(ValueError, match="shape"):
        exported.call(weights, *(array[:1] for array in (image1, image2, flow)))


def test_bad_arguments_are_refused_before_anything_is_written(tiny_model, tmp_path):
    model, variables = tiny_model
    path = tmp_path / "model.gldx"
    arguments = dict(height=HEIGHT, width=WIDTH)
    with pytest.raises(ValueError, match=r"unknown platform\(s\) \['gpu'\]"):
        export.export_model(model, variables, path, platforms=("gpu",), **arguments)
    with pytest.raises(ValueError, match="twice"):
        export.export_model(model, variables, path, platforms=("cpu", "cpu"), **arguments)
    with pytest.raises(ValueError, match="batch_size must be a positive integer"):
        export.export_model(model, variables, path, batch_size=0, **arguments)
    with pytest.raises(ValueError, match="height must be a positive integer"):
        export.export_model(model, variables, path, height=0, width=WIDTH)
    with pytest.raises(ValueError, match="needs a fixed batch size"):
        export.export_model(model, variables, path, formulation="vmap", **arguments)
    with pytest.raises(ValueError, match="is a directory"):
        export.export_model(model, variables, tmp_path, **arguments)
    baseline = registry.make_model("small_encdec")
    with pytest.raises(ValueError, match="'small_encdec' has no per-example filters"):
        export.export_model(baseline, {}, path, formulation="fused", **arguments)
    assert list(tmp_path.iterdir()) == []
