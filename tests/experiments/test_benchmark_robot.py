"""The robot-loop benchmark suite (experiments/benchmarks/robot.py); no timing assertions."""

import json
import os
import subprocess
import sys

import numpy as np
import pytest
from conftest import REPO_ROOT

from experiments.benchmarks import robot


@pytest.mark.slow
def test_quick_run_times_every_stage_of_both_networks_and_the_runtime(tmp_path):
    output = tmp_path / "robot.json"
    completed = subprocess.run(
        [sys.executable, "-m", "experiments.benchmark", "--suite=robot", "--quick"]
        + [f"--output={output}"],
        cwd=REPO_ROOT,
        capture_output=True,
        text=True,
        env=dict(os.environ, JAX_PLATFORMS="cpu"),
        timeout=600,
    )
    assert completed.returncode == 0, completed.stderr[-3000:]
    assert "PWC-Net" in completed.stdout and "exported" in completed.stdout

    record = json.loads(output.read_text())
    assert record["suite"] == "robot"
    result = record["result"]
    assert result["settings"]["quick"] and result["settings"]["repeats"] == 1
    assert [row["network"] for row in result["rows"]] == ["jit (live)", "exported", "runtime"]
    runtime = result["rows"].pop()
    # The runtime is timed end to end, frames to metric depth with DIS inside.
    assert runtime["flow_estimator"] == "dis" and runtime["load_s"] > 0
    assert 0 < runtime["total"]["median_ms"] and runtime["flow"] is None
    for row in result["rows"]:
        assert (row["height"], row["width"]) == robot.QUICK_SIZES[0]
        for stage in robot.STAGES:
            assert 0 < row[stage]["median_ms"] <= row[stage]["p90_ms"]
        # The stages are consecutive intervals of one loop: they add up to its total.
        parts = sum(row[stage]["median_ms"] for stage in ("flow", "model", "scale"))
        assert row["total"]["median_ms"] == pytest.approx(parts, rel=1e-6)
    assert result["rows"][0]["compile_s"] > 0
    assert result["rows"][1]["export_s"] > 0 and result["rows"][1]["load_s"] > 0
    assert result["reference"]["model_ms"] == 4.0 and result["reference"]["flow_ms"] == 45.0


def test_the_range_reading_is_the_valid_pixel_nearest_the_centre():
    depth = np.full((5, 7), 2.0, np.float32)
    depth[2, 3] = np.inf  # the centre pixel sees nothing
    depth[1, 3] = 0.0
    depth[2, 2] = 4.5
    pixel, distance = robot._range_reading(depth)
    assert (pixel, distance) == ([2.0, 2.0], 4.5)  # (u, v) = (column, row)
    with pytest.raises(ValueError, match="no valid depth"):
        robot._range_reading(np.zeros((3, 3), np.float32))


def test_at_least_one_repeat():
    with pytest.raises(ValueError, match="repeats must be >= 1, got 0"):
        robot.run(repeats=0, quick=False)


def test_times_a_given_exported_file_end_to_end(tmp_path):
    from conftest import TINY_MODEL, random_variables

    from gld.inference import export
    from gld.models import registry

    model = registry.make_model("global_local", **TINY_MODEL)
    path = tmp_path / "model.gldx"
    variables = random_variables(model, 24, 32, seed=0)
    export.export_model(model, variables, path, height=24, width=32)
    result = robot.run(repeats=2, quick=False, artifact=path, log=lambda _: None)
    (row,) = result["rows"]
    assert (row["network"], row["height"], row["width"]) == ("runtime", 24, 32)
    assert 0 < row["total"]["median_ms"] <= row["total"]["p90_ms"]
    assert result["settings"]["artifact"] == str(path)
