"""Tests of the benchmark launcher (python -m experiments.benchmark); no timing assertions."""

import json
import os
import subprocess
import sys
import textwrap

import pytest
from conftest import REPO_ROOT

from experiments.benchmarks import model as model_benchmark
from gld.models import filter_banks

FAKE_TORCH_FIGURES = {
    "eager": {"forward_b1_ms": 12.0, "forward_b16_ms": 400.0, "train_b16_ms": 1250.0},
    "compiled": {"forward_b1_ms": 9.0, "forward_b16_ms": 250.0, "train_b16_ms": 1300.0},
}


@pytest.fixture
def fake_torch_reference(tmp_path):
    """A stand-in for torch_reference.py that prints fixed figures and its arguments."""
    script = tmp_path / "fake_reference.py"
    script.write_text(
        textwrap.dedent(
            f"""
            import json, sys
            figures = {FAKE_TORCH_FIGURES!r}
            if "--no-compile" in sys.argv:
                del figures["compiled"]
            print(json.dumps({{"torch": "fake", "argv": sys.argv[1:], **figures}}))
            """
        )
    )
    return script


@pytest.mark.slow
def test_quick_run_writes_every_figure(tmp_path, fake_torch_reference):
    output = tmp_path / "out" / "bench.json"
    command = [
        sys.executable,
        "-m",
        "experiments.benchmark",
        "--quick",
        "--formulations=fused",
        f"--output={output}",
        f"--torch_python={sys.executable}",
        f"--torch_reference={fake_torch_reference}",
        "--torch_rounds=2",
    ]
    env = dict(os.environ, JAX_PLATFORMS="cpu")
    completed = subprocess.run(
        command, cwd=REPO_ROOT, capture_output=True, text=True, env=env, timeout=600
    )
    assert completed.returncode == 0, completed.stderr[-3000:]
    assert "global_local/fused" in completed.stdout

    record = json.loads(output.read_text())
    assert record["suite"] == "model"
    result = record["result"]
    assert [row["formulation"] for row in result["rows"]] == ["fused"]
    for row in result["rows"]:
        assert "error" not in row, row
        assert (row["height"], row["width"]) == (16, 24)
        latency = row["forward_b1"]
        assert 0 < latency["median_s"] <= latency["p90_s"]
        assert row["forward_b2"]["pairs_per_s"] == pytest.approx(2 / row["forward_b2"]["median_s"])
        assert row["train_b2"]["median_s"] > 0 and row["train_b2"]["compile_s"] > 0
        assert row["peak_rss_mb"] > 50
    # Flops come from the vmap reference's cost analysis; a step costs more than a forward.
    row = result["rows"][0]
    assert row["train_b2"]["gflop"] > row["forward_b2"]["gflop"] > row["forward_b1"]["gflop"] > 0
    # The reference ran before and after, and its figures (ms) are reported in seconds.
    assert len(result["torch"]["rounds"]) == 2
    assert result["torch"]["median_s"]["eager"]["train_b16_s"] == pytest.approx(1.25)
    # 16x24 at batch 2 is not the reference's problem: no goal ratios.
    assert not result["settings"]["torch_comparable"]
    assert all("vs_torch" not in row for row in result["rows"])
    assert result["default_formulation"]["cpu"] in filter_banks.FORMULATIONS


def test_goal_ratios_against_the_reference():
    row = {
        "train_b16": {"median_s": 1.0},
        "forward_b16": {"median_s": 0.5},
        "forward_b1": {"median_s": 0.006},
    }
    torch = model_benchmark._torch_summary([FAKE_TORCH_FIGURES])
    ratios = model_benchmark.goal_ratios(row, torch)
    assert ratios["train_b16_vs_eager (goal <= 0.8)"] == pytest.approx(1.0 / 1.25)
    assert ratios["forward_b16_vs_compiled (goal <= 1)"] == pytest.approx(0.5 / 0.25)
    assert ratios["forward_b1_vs_eager (goal <= 1)"] == pytest.approx(0.006 / 0.012)


def test_unknown_suite_and_formulation_are_refused(tmp_path):
    completed = subprocess.run(
        [sys.executable, "-m", "experiments.benchmark", "--suite=nope"],
        cwd=REPO_ROOT,
        capture_output=True,
        text=True,
        env=dict(os.environ, JAX_PLATFORMS="cpu"),
    )
    assert completed.returncode != 0 and "--suite must be one of" in completed.stderr
    with pytest.raises(ValueError, match="unknown formulations"):
        model_benchmark.run(formulations=["nope"])
