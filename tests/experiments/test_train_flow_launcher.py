"""experiments.train_flow runs end to end in a subprocess on the tiny benchmark."""

import json

import jax
import jax.numpy as jnp
import pytest
from conftest import launch

from gld.runs import trained_flow

# A small network and a few steps keep each launch to compile time.
TINY_FLAGS = [
    "--feature_channels=8,12,16",
    "--estimator_channels=16,8",
    "--context_channels=8",
    "--max_displacement=2",
    "--batch_size=4",
    "--warmup_steps=1",
    "--log_every=2",
    "--checkpoint_every=2",
    "--latency_repeats=2",
]


def _launch(args, data_dir):
    return launch(
        "experiments.train_flow",
        "--dataset=gld_scenes/tiny",
        f"--data_dir={data_dir}",
        *args,
        timeout=600,
    )


def _records(workdir):
    return [json.loads(line) for line in (workdir / "metrics.jsonl").read_text().splitlines()]


@pytest.mark.slow
def test_train_flow_trains_evaluates_and_resumes(tiny_scenes_dir, tmp_path):
    workdir = tmp_path / "flow"
    result = _launch(
        [f"--workdir={workdir}", "--steps=4", "--eval_every=2", *TINY_FLAGS], tiny_scenes_dir
    )
    assert result.returncode == 0, result.stderr[-3000:]
    assert "parameters flow_net:" in result.stdout
    records = _records(workdir)
    assert [r["step"] for r in records if r["split"] == "train"] == [2, 4]
    assert [r["step"] for r in records if r["split"] == "test"] == [2, 4]
    assert all(r["dis_epe"] > 0 for r in records if r["split"] == "test")
    stored = json.loads((workdir / "flow_config.json").read_text())
    assert stored["architecture"]["feature_channels"] == [8, 12, 16]
    assert stored["config"]["height"] == 48 and stored["config"]["steps"] == 4
    report = json.loads((workdir / "eval" / "flow.json").read_text())
    assert report["step"] == 4
    assert report["methods"]["flow_net"]["count"] == report["methods"]["dis"]["count"] == 16
    assert report["parameters"] > 0 and report["latency_batch1"]["median_ms"] > 0
    table = (workdir / "eval" / "flow_table.md").read_text()
    assert "| flow_net (learned, PWC-Net style) |" in table and table in result.stdout

    # the same command with more steps resumes from the last checkpoint
    resumed = _launch(
        [f"--workdir={workdir}", "--steps=6", "--eval_every=0", *TINY_FLAGS], tiny_scenes_dir
    )
    assert resumed.returncode == 0, resumed.stderr[-3000:]
    assert "resumed from step 4" in resumed.stdout
    assert "steps 4 -> 6" in resumed.stdout
    assert [r["step"] for r in _records(workdir) if r["split"] == "train"] == [2, 4, 6]
    steps = sorted(int(p.name) for p in (workdir / "checkpoints").iterdir() if p.name.isdigit())
    assert steps == [4, 6]
    assert json.loads((workdir / "eval" / "flow.json").read_text())["step"] == 6

    # the trained network loads back from the workdir
    model, variables, config, step = trained_flow.load_flow_run(workdir)
    assert step == 6 and config.steps == 6 and tuple(model.feature_channels) == (8, 12, 16)
    images = jnp.zeros((1, 48, 64, 3))
    assert jax.jit(model.apply)(variables, images, images)["flow"].shape == (1, 48, 64, 2)

    # another architecture in the same workdir is refused, naming the option
    refused = _launch(
        [f"--workdir={workdir}", "--steps=6", *TINY_FLAGS, "--max_displacement=3"],
        tiny_scenes_dir,
    )
    assert refused.returncode != 0
    assert "max_displacement: 2 in the workdir vs 3" in refused.stderr
    assert json.loads((workdir / "flow_config.json").read_text()) == {
        **stored,
        "config": {**stored["config"], "steps": 6, "eval_every": 0},
    }


def test_bad_flags_stop_the_launcher_before_anything_is_written(tiny_scenes_dir, tmp_path):
    workdir = tmp_path / "never"
    # 6 pyramid levels need sizes divisible by 64; gld_scenes/tiny is 64x48
    result = _launch(
        [f"--workdir={workdir}", "--feature_channels=4,4,4,4,4,4", "--warmup_steps=0"],
        tiny_scenes_dir,
    )
    assert result.returncode != 0
    assert "feature_channels" in result.stderr and "divisible by 64" in result.stderr
    result = _launch([f"--workdir={workdir}", "--batch_size=0"], tiny_scenes_dir)
    assert result.returncode != 0 and "batch_size" in result.stderr
    assert not workdir.exists()
