"""Tests of the benchmark launcher (python -m experiments.benchmark); no timing assertions."""

import json
import os
import subprocess
import sys
import textwrap

import pytest
from conftest import REPO_ROOT

from experiments.benchmarks import model as model_benchmark
from experiments.benchmarks import model_tables, torch_pairs
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
        "--pairs=2",
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
    # The formulation asked for alternates with the reference (the platform's default
    # when it is among those asked for): one row per pair.
    assert [row["formulation"] for row in result["rows"]] == ["fused", "fused"]
    assert [pair["gld"] for pair in result["pairs"]] == result["rows"]
    assert result["gemm"]["best_gflops_per_s"] >= result["gemm"]["median_gflops_per_s"] > 0
    for row in result["rows"]:
        assert "error" not in row, row
        assert (row["height"], row["width"]) == (16, 24)
        latency = row["forward_b1"]
        assert 0 < latency["median_s"] <= latency["p90_s"]
        assert row["forward_b2"]["pairs_per_s"] == pytest.approx(2 / row["forward_b2"]["median_s"])
        assert row["train_b2"]["median_s"] > 0 and row["train_b2"]["compile_s"] > 0
        assert row["peak_rss_mb"] > 50
        # Batch 2 splits over the two CPU devices; batch 1 cannot.
        assert row["devices"] == 2 and row["train_b2"]["devices"] == 2
        assert row["forward_b1"]["devices"] == 1
    # Flops come from the vmap reference's cost analysis; a step costs more than a forward.
    row = result["rows"][0]
    assert row["train_b2"]["gflop"] > row["forward_b2"]["gflop"] > row["forward_b1"]["gflop"] > 0
    # The reference ran once per pair, and its figures (ms) are reported in seconds.
    assert len(result["torch"]["rounds"]) == 2
    assert result["torch"]["median_s"]["eager"]["train_b16_s"] == pytest.approx(1.25)
    # 16x24 at batch 2 is not the reference's problem: no goal ratios.
    assert not result["settings"]["torch_comparable"]
    assert all("vs_torch" not in row for row in result["rows"])
    assert result["default_formulation"]["cpu"] in filter_banks.FORMULATIONS


def test_a_model_without_filter_banks_is_measured_without_a_formulation(monkeypatch):
    measured = []

    def fake_measure(arguments):
        measured.append((arguments["model_name"], arguments["formulation"]))
        formulation = arguments["formulation"] or "-"
        return {"model": arguments["model_name"], "formulation": formulation, "error": "fake"}

    monkeypatch.setattr(model_benchmark, "_measure_in_subprocess", fake_measure)
    monkeypatch.setattr(model_benchmark, "_in_subprocess", lambda kind, arguments: {})
    model_benchmark.run(
        models=["small_encdec", "global_local"],
        formulations=["fused", "vmap"],
        pairs=2,
        log=lambda line: None,
    )
    # The first model pairs with the reference as it is; the formulations are the
    # global-local model's alone.
    assert measured == [
        ("small_encdec", None),
        ("small_encdec", None),
        ("global_local", "fused"),
        ("global_local", "vmap"),
    ]


def test_goal_ratios_against_the_reference():
    row = {
        "train_b16": {"median_s": 1.0},
        "forward_b16": {"median_s": 0.5},
        "forward_b1": {"median_s": 0.006},
    }
    torch = torch_pairs.torch_summary([FAKE_TORCH_FIGURES])
    ratios = torch_pairs.goal_ratios(row, torch)
    assert ratios["train_b16_vs_eager"] == pytest.approx(1.0 / 1.25)
    assert ratios["train_b16_vs_compiled"] == pytest.approx(1.0 / 1.3)
    assert ratios["forward_b16_vs_compiled"] == pytest.approx(0.5 / 0.25)
    assert ratios["forward_b1_vs_eager"] == pytest.approx(0.006 / 0.012)


def _pair(train_s: float, eager_train_ms: float) -> dict:
    gld = {
        "train_b16": {"median_s": train_s},
        "forward_b16": {"median_s": 0.2},
        "forward_b1": {"median_s": 0.01},
    }
    reference = json.loads(json.dumps(FAKE_TORCH_FIGURES))
    reference["eager"]["train_b16_ms"] = eager_train_ms
    return {"torch": {"torch": "9.9", **reference}, "gld": gld}


def test_pairs_are_compared_each_with_its_own_reference():
    pairs = [_pair(0.5, 1000.0), _pair(0.6, 2000.0), _pair(0.4, 1000.0)]
    summary = torch_pairs.summarise_pairs(pairs)
    per_pair = [ratios["train_b16_vs_eager"] for ratios in summary["ratios_per_pair"]]
    assert per_pair == pytest.approx([0.5, 0.3, 0.4])
    assert summary["train_b16_vs_eager"] == pytest.approx({"median": 0.4, "min": 0.3, "max": 0.5})
    assert summary["gld_train_b16_s"]["median"] == pytest.approx(0.5)
    # The reference's train step varied 2x across the pairs: noisy.
    assert summary["torch_noisy"]
    assert not torch_pairs.summarise_pairs([_pair(0.5, 1000.0), _pair(0.5, 1100.0)])["torch_noisy"]


def _result(pairs: list[dict], **overrides) -> dict:
    """A model-suite result of the CPU (2 pairs at 256x192) around `pairs`."""
    return {
        "pairs": pairs,
        "summary": torch_pairs.summarise_pairs(pairs),
        "gemm": {"size": 2048, "best_gflops_per_s": 150.0, "median_gflops_per_s": 140.0},
        "settings": {
            "height": 192,
            "width": 256,
            "cpu_devices": 2,
            "pairs": 2,
            "repeats": 5,
            "train_batch_size": 16,
            "load_average": (1.0, 1.0, 1.0),
        },
        "machine": "a CPU, 2 cores",
        "date": "2026-11-27 05:00 UTC",
        "default_formulation": {"cpu": "fused", "gpu": "vmap"},
        **overrides,
    }


def test_the_readme_table_is_rewritten_between_its_markers():
    pairs = [_pair(0.5, 1000.0), _pair(0.6, 1100.0)]
    result = _result(
        pairs,
        summary={
            **torch_pairs.summarise_pairs(pairs),
            "train_share_of_gemm_peak": [0.3, 0.25],
        },
    )
    table = model_tables.markdown_table(result, "abc1234")
    assert "commit abc1234" in table and "PyTorch 9.9" in table
    # Each pair's ratio against its own reference, and the GEMM share of each pair.
    assert "| 0.50 / 0.55 |" in table and "30%, 25%" in table
    readme = f"intro\n{model_tables.README_START}\nold table\n{model_tables.README_END}\nrest\n"
    rewritten = model_tables.replace_readme_table(readme, table)
    assert "old table" not in rewritten and table in rewritten
    assert rewritten.startswith("intro\n") and rewritten.endswith("rest\n")
    assert model_tables.replace_readme_table(rewritten, table) == rewritten
    with pytest.raises(ValueError, match="no speed table markers"):
        model_tables.replace_readme_table("no markers", table)


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


def test_a_device_reference_runs_through_the_synchronising_runner(tmp_path):
    """With a device, the reference is timed by torch_on_device.py, told the device and
    the reference file; on the CPU the reference runs itself."""
    echo = tmp_path / "python"
    program = 'import json, sys; print(json.dumps({"argv": sys.argv[1:]}))'
    echo.write_text(f"#!/bin/sh\nexec {sys.executable} -c '{program}' \"$@\"\n")
    echo.chmod(0o755)
    on_device = torch_pairs.run_torch_reference(str(echo), "ref.py", 7, True, device="cuda")
    runner, *arguments = on_device["argv"]
    assert runner.endswith("experiments/benchmarks/torch_on_device.py")
    assert arguments == ["--device=cuda", "--reference=ref.py", "--repeats", "7"]
    on_cpu = torch_pairs.run_torch_reference(str(echo), "ref.py", 7, False)
    assert on_cpu["argv"] == ["ref.py", "--repeats", "7", "--no-compile"]


def test_a_gpu_result_goes_to_the_gpu_table_in_milliseconds():
    pairs = [_pair(0.005, 10.0), _pair(0.006, 11.0)]
    rows = [pair["gld"] for pair in pairs] + [
        {"formulation": "fused", "train_b16": {"median_s": 0.0123}}
    ]
    for row in rows[:2]:
        row["formulation"] = "vmap"
    result = _result(
        pairs,
        rows=rows,
        gemm={"size": 8192, "best_gflops_per_s": 4.0e5, "median_gflops_per_s": 3.9e5},
        machine="NVIDIA H200 (host: a CPU, 16 cores)",
        paired_formulation="vmap",
        backend="gpu",
    )
    table = model_tables.markdown_table(result, "abc1234")
    assert "the GPU default `vmap` on one device" in table and "TF32" in table
    # The train step in milliseconds, and the other formulation beside the paired one.
    assert "| Adam train step, batch 16 [ms] | 5.50 (5.00-6.00) |" in table
    assert "`fused` 12.30 ms" in table and "`vmap`" not in table.split("same run:")[1]
    readme = (
        f"{model_tables.README_START}\ncpu table\n{model_tables.README_END}\n"
        f"{model_tables.GPU_README_START}\nold\n{model_tables.GPU_README_END}\n"
    )
    rewritten = model_tables.replace_readme_table(readme, table, "gpu")
    assert "cpu table" in rewritten and "old" not in rewritten and table in rewritten


@pytest.mark.parametrize(
    "record, message",
    [
        ({"suite": "robot", "result": {}}, "is not a model-suite result"),
        ({"suite": "model", "result": {"pairs": []}}, "is not a complete model-suite result"),
    ],
)
def test_readme_from_refuses_what_is_not_a_model_result(tmp_path, record, message):
    readme = tmp_path / "README.md"
    readme.write_text(f"{model_tables.README_START}\nold\n{model_tables.README_END}\n")
    before = readme.read_text()
    path = tmp_path / "result.json"
    path.write_text(json.dumps(record))
    with pytest.raises(ValueError, match=message):
        model_tables.readme_from(readme, path)
    assert readme.read_text() == before
    # A complete result goes in.
    result = _result([_pair(0.5, 1000.0)])
    path.write_text(json.dumps({"suite": "model", "commit": "abc1234", "result": result}))
    assert model_tables.readme_from(readme, path) == "cpu"
    assert "commit abc1234" in readme.read_text() and "old" not in readme.read_text()
