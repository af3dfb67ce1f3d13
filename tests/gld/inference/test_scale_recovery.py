"""A workdir's metric scale recovery (gld/inference/scale_recovery.py): the workdir and the
dataset are checked, by their flags' names, before the model is loaded. The measurement
itself: tests/gld/inference/test_scale.py, and the launcher's end-to-end test."""

from types import SimpleNamespace

import pytest
from conftest import tiny_train_config

from gld.arguments import ArgumentError
from gld.inference import scale_recovery
from gld.runs import workdir as workdir_lib


def test_a_workdir_without_a_config_is_refused_before_the_dataset_is_built(tmp_path):
    def prepare_dataset(name):
        raise AssertionError("prepared")

    with pytest.raises(ArgumentError, match="--workdir: .*missing"):
        scale_recovery.measure_workdir(tmp_path / "missing", prepare_dataset=prepare_dataset)


def test_the_dataset_defaults_to_the_workdirs_and_needs_train_and_test(tmp_path):
    workdir_lib.write_run_config(tmp_path, tiny_train_config())
    asked = []

    def prepare_dataset(name):
        asked.append(name)
        info = SimpleNamespace(splits={"test": None}, full_name=f"{name}/1.0.0")
        return SimpleNamespace(info=info)

    with pytest.raises(ArgumentError, match="--dataset: gld_scenes/tiny/1.0.0 needs train and"):
        scale_recovery.measure_workdir(tmp_path, prepare_dataset=prepare_dataset)
    with pytest.raises(ArgumentError, match="--dataset: demon/sun3d/1.0.0 needs"):
        scale_recovery.measure_workdir(
            tmp_path, prepare_dataset=prepare_dataset, dataset="demon/sun3d"
        )
    assert asked == ["gld_scenes/tiny", "demon/sun3d"]
