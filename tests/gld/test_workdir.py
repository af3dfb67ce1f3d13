"""A run's workdir: the stored configuration, the architecture guard, old workdirs."""

import json

import pytest
from conftest import TINY_MODEL, tiny_train_config

from gld import model as model_lib
from gld import train, workdir


def test_a_workdir_refuses_another_architecture_listing_the_flags(tiny_scenes, tmp_path):
    source = tiny_scenes.as_data_source("train")
    train.train_and_evaluate(
        tiny_train_config(steps=2), tmp_path, source, progress=False, print_fn=lambda _: None
    )
    other = tiny_train_config(model_config=dict(TINY_MODEL, global_dim=3, use_coordinates=False))
    with pytest.raises(ValueError, match="global_dim.*use_coordinates"):
        train.train_and_evaluate(other, tmp_path, source, progress=False, print_fn=lambda _: None)
    # a speed-only choice is not architecture
    same = tiny_train_config(steps=2, model_config=dict(TINY_MODEL, filter_formulation="vmap"))
    workdir.write_run_config(tmp_path, same)


def test_a_run_stores_every_architecture_value_and_old_runs_keep_theirs(tmp_path):
    config = tiny_train_config()
    workdir.write_run_config(tmp_path, config)
    stored = json.loads((tmp_path / "config.json").read_text())
    # Defaults are written out, so a later change of a default cannot change this run.
    assert stored["architecture"]["flow_scale"] == 10.0
    assert stored["config"]["model_config"]["global_norm"] == "none"
    assert workdir.load_run_config(tmp_path).model_config["flow_scale"] == 10.0

    # A workdir written before flow_scale existed was trained on unscaled flow.
    old = tmp_path / "old"
    old.mkdir()
    for section in ("architecture", "config"):
        values = stored[section] if section == "architecture" else stored[section]["model_config"]
        for key in ("flow_scale", "global_norm", "modulation_scale"):
            values.pop(key)
    (old / "config.json").write_text(json.dumps(stored))
    loaded = workdir.load_run_config(old)
    assert loaded.model_config["flow_scale"] == 1.0
    assert model_lib.make_model(loaded.model, **loaded.model_config).flow_scale == 1.0
    with pytest.raises(ValueError, match="flow_scale: 1.0 in the workdir vs 10.0 now"):
        workdir.write_run_config(old, config)


def test_a_workdir_stored_with_the_old_flow_key_loads_as_flow_source(tmp_path):
    workdir.write_run_config(tmp_path, tiny_train_config(flow_source="gt"))
    stored = json.loads((tmp_path / "config.json").read_text())
    assert stored["config"]["flow_source"] == "gt"
    # Workdirs written before the rename stored the flow under "flow".
    stored["config"]["flow"] = stored["config"].pop("flow_source")
    (tmp_path / "config.json").write_text(json.dumps(stored))
    assert workdir.load_run_config(tmp_path).flow_source == "gt"
