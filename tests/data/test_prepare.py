"""Tests of data/__init__.py's `prepare`: a built dataset is reused only for the input
it was built from (files of the manual directory, build options), or rebuilt on request."""

from __future__ import annotations

import json
import logging
import shutil

import demon_files
import h5py
import numpy as np
import pytest

import data
from gld import records


def _write_recording(manual_dir, scene, name="custom_train.h5"):
    """A tiny `demon/custom` file with one two-view scene named `scene`."""
    manual_dir.mkdir(parents=True, exist_ok=True)
    views = demon_files.moving_views(np.random.default_rng(len(scene)), 2, 24, 32)
    with h5py.File(manual_dir / name, "w") as h5_file:
        h5_file.create_group(".config")
        demon_files.write_scene(h5_file, scene, views)
    return manual_dir / name


def _train_ids(builder):
    return sorted(records.decode(record)["id"] for record in builder.as_data_source("train"))


def test_reuse_for_another_recording_is_refused_naming_the_change(tmp_path):
    datasets = tmp_path / "datasets"
    first = _write_recording(tmp_path / "a", "kitchen")
    second = _write_recording(tmp_path / "b", "garden")
    built = data.prepare("demon/custom", datasets, tmp_path / "a")
    assert _train_ids(built) == ["custom_train.h5/kitchen/0-1"]
    assert built.info.metadata["sources"]["train"]["custom_train.h5"]["path"] == str(
        first.resolve()
    )

    with pytest.raises(ValueError) as refused:
        data.prepare("demon/custom", datasets, tmp_path / "b")
    message = str(refused.value)
    assert "train split: custom_train.h5 changed" in message
    assert f"was {first.resolve()}, now {second.resolve()}" in message
    assert "--rebuild" in message and "another --data_dir" in message

    # Without a manual directory, or with the same files elsewhere: reused as built.
    assert _train_ids(data.prepare("demon/custom", datasets)) == ["custom_train.h5/kitchen/0-1"]
    shutil.copytree(tmp_path / "a", tmp_path / "a_copy")
    reused = data.prepare("demon/custom", datasets, tmp_path / "a_copy")
    assert _train_ids(reused) == ["custom_train.h5/kitchen/0-1"]

    added = _write_recording(tmp_path / "a_copy", "hall", "custom_test_lab.h5")
    with pytest.raises(ValueError, match=f"test split: custom_test_lab.h5 added \\({added}"):
        data.prepare("demon/custom", datasets, tmp_path / "a_copy")


def test_rebuild_replaces_the_dataset_only_once_the_new_build_succeeds(tmp_path):
    datasets = tmp_path / "datasets"
    _write_recording(tmp_path / "a", "kitchen")
    _write_recording(tmp_path / "b", "garden")
    truncated = _write_recording(tmp_path / "truncated", "garden")
    truncated.write_bytes(truncated.read_bytes()[:1000])
    data.prepare("demon/custom", datasets, tmp_path / "a")

    with pytest.raises(ValueError, match="custom_train.h5 is not a readable HDF5 file"):
        data.prepare("demon/custom", datasets, tmp_path / "truncated", rebuild=True)
    assert _train_ids(data.prepare("demon/custom", datasets, tmp_path / "a")) == [
        "custom_train.h5/kitchen/0-1"
    ]

    rebuilt = data.prepare("demon/custom", datasets, tmp_path / "b", rebuild=True)
    assert _train_ids(rebuilt) == ["custom_train.h5/garden/0-1"]
    assert not list(datasets.glob(".rebuild-*"))  # the staging folder is gone
    assert _train_ids(data.prepare("demon/custom", datasets, tmp_path / "b")) == [
        "custom_train.h5/garden/0-1"
    ]
    with pytest.raises(ValueError, match="custom_train.h5 changed"):
        data.prepare("demon/custom", datasets, tmp_path / "a")


def test_reuse_with_another_build_option_is_refused(tmp_path):
    datasets = tmp_path / "datasets"
    _write_recording(tmp_path / "a", "kitchen")
    data.prepare("demon/custom", datasets, tmp_path / "a")  # depth_resampling: demon
    with pytest.raises(ValueError) as refused:
        data.prepare("demon/custom", datasets, tmp_path / "a", depth_resampling="centred")
    assert "train split: depth_resampling='centred' given, built with depth_resampling='demon'" in (
        str(refused.value)
    )
    # The options it was built with, and options that do not shape the records, reuse it.
    data.prepare("demon/custom", datasets, depth_resampling="demon", strict=True)


def test_a_build_without_recorded_sources_is_reused_with_a_warning(tmp_path, caplog):
    datasets = tmp_path / "datasets"
    _write_recording(tmp_path / "a", "kitchen")
    builder = data.prepare("demon/custom", datasets, tmp_path / "a")
    metadata_file = builder.data_path / "metadata.json"
    metadata = json.loads(metadata_file.read_text())
    del metadata["sources"]
    metadata_file.write_text(json.dumps(metadata))
    _write_recording(tmp_path / "b", "garden")
    with caplog.at_level(logging.WARNING, logger="data"):
        reused = data.prepare("demon/custom", datasets, tmp_path / "b")
    assert _train_ids(reused) == ["custom_train.h5/kitchen/0-1"]
    assert "records no source files" in caplog.text and "--rebuild" in caplog.text


def test_datasets_without_a_manual_directory_are_unaffected(tiny_scenes_dir, tmp_path):
    builder = data.prepare("gld_scenes/tiny", tiny_scenes_dir, tmp_path, workers=2)
    assert builder.info.splits["train"].num_examples == 32


def test_a_wrong_dataset_or_manual_directory_is_one_line_naming_the_flag(tmp_path):
    from gld.arguments import ArgumentError

    data_dir = tmp_path / "datasets"
    empty = tmp_path / "empty"
    empty.mkdir()
    cases = [
        (dict(dataset="scenes/small"), "--dataset: unknown dataset 'scenes'; valid: "),
        (
            dict(dataset="gld_scenes/smal"),
            "--dataset=gld_scenes/smal: unknown config 'smal' of dataset 'gld_scenes'",
        ),
        (
            dict(dataset="demon/sun3d", manual_dir=tmp_path / "none"),
            f"--manual_dir={tmp_path / 'none'}: no such directory (",
        ),
        (
            dict(dataset="demon/sun3d", manual_dir=empty),
            f"--manual_dir={empty}: the directory is empty (",
        ),
        (
            dict(dataset="demon/sun3d"),
            f"--manual_dir: demon/sun3d is built from files you provide; give their folder "
            f"(the default, {data_dir / 'downloads' / 'manual'}, is missing or empty;",
        ),
    ]
    for arguments, start in cases:
        with pytest.raises(ArgumentError) as refused:
            data.prepare(data_dir=data_dir, **arguments)
        assert str(refused.value).startswith(start) and "\n" not in str(refused.value)
    assert not data_dir.exists()  # nothing written


def test_missing_demon_files_are_one_line_naming_them(tmp_path):
    from gld.arguments import ArgumentError

    manual = tmp_path / "manual"
    manual.mkdir()
    (manual / "notes.txt").write_text("not a DeMoN file\n")
    with pytest.raises(FileNotFoundError) as refused:
        data.prepare("demon/sun3d", tmp_path / "datasets", manual)
    assert isinstance(refused.value, ArgumentError)
    line = str(refused.value)
    assert line.startswith(f"--manual_dir={manual}: demon/sun3d: none of [")
    assert "'sun3d_test.h5'" in line and "\n" not in line
