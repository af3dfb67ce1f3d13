import importlib.util
import json

import demon_files
import h5py
import numpy as np
import pytest
from conftest import launch, run_python

import data
from gld import records


def _build(*args):
    return launch("data.build", *args, timeout=300)


def test_build_command_builds_and_reports(tmp_path):
    result = _build("--dataset=gld_scenes/tiny", f"--data_dir={tmp_path}", "--workers=2")
    assert result.returncode == 0, result.stderr[-2000:]
    assert "gld_scenes/tiny train: 32 pairs" in result.stdout
    assert "gld_scenes/tiny test: 16 pairs" in result.stdout
    assert list((tmp_path / "gld_scenes" / "tiny").glob("*/*.array_record*"))


def test_build_command_lists_valid_configs_for_an_unknown_one(tmp_path):
    result = _build("--dataset=gld_scenes/huge", f"--data_dir={tmp_path}")
    assert result.returncode != 0
    assert "gld_scenes/tiny" in result.stderr and "gld_scenes/small" in result.stderr


_PLAIN_TFDS_BUILD = """
import importlib.util, json, sys
import tensorflow_datasets as tfds
import data.gld_scenes.gld_scenes_dataset_builder  # registers gld_scenes
builder = tfds.builder("gld_scenes/tiny", data_dir=sys.argv[1])
builder.download_and_prepare()
source = tfds.data_source("gld_scenes/tiny", data_dir=sys.argv[1], split="test")
print(json.dumps({
    "splits": {name: info.num_examples for name, info in builder.info.splits.items()},
    "file_format": builder.info.file_format.value,
    "test_records": len(source),
    "tensorflow_loaded": "tensorflow" in sys.modules,
}))
"""


def test_plain_tfds_builder_call_works_without_tensorflow(tmp_path):
    """`tfds.builder(...).download_and_prepare()` writes array_record, which needs no
    TensorFlow (TFDS's own default, TFRecord, fails while finalising a split)."""
    if importlib.util.find_spec("tensorflow") is not None:
        pytest.skip("TensorFlow is installed: this checks the TensorFlow-free install")
    result = run_python(_PLAIN_TFDS_BUILD, str(tmp_path))
    built = json.loads(result.stdout.strip().splitlines()[-1])
    assert built == {
        "splits": {"train": 32, "test": 16},
        "file_format": "array_record",
        "test_records": 16,
        "tensorflow_loaded": False,
    }
    assert len(list((tmp_path / "gld_scenes" / "tiny").glob("*/*.array_record-*"))) == 2


def test_build_command_rebuilds_from_changed_files_on_request(tmp_path):
    """--rebuild replaces a demon/custom build made from another recording (which
    `data.prepare`, and so the command without --rebuild, refuses: test_prepare.py)."""
    manual_dir = tmp_path / "robot"
    manual_dir.mkdir()
    views = demon_files.moving_views(np.random.default_rng(0), 2, 24, 32)
    recording = manual_dir / "custom_train.h5"
    with h5py.File(recording, "w") as h5_file:
        demon_files.write_scene(h5_file, "kitchen", views)
    data.prepare("demon/custom", tmp_path / "datasets", manual_dir)
    with h5py.File(recording, "w") as h5_file:  # the same name, another recording
        demon_files.write_scene(h5_file, "garden", views)
        demon_files.write_scene(h5_file, "hall", views[::-1])
    command = ["--dataset=demon/custom", f"--data_dir={tmp_path / 'datasets'}"]
    command.append(f"--manual_dir={manual_dir}")
    result = _build(*command, "--rebuild")
    assert result.returncode == 0, result.stderr[-2000:]
    assert "demon/custom train: 2 pairs" in result.stdout
    builder = data.prepare("demon/custom", tmp_path / "datasets", manual_dir)
    ids = sorted(records.decode(record)["id"] for record in builder.as_data_source("train"))
    assert ids == ["custom_train.h5/garden/0-1", "custom_train.h5/hall/0-1"]
