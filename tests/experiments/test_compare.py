"""`python -m experiments.compare` trains, evaluates and tabulates on the tiny benchmark."""

import json
import os
import subprocess
import sys

import h5py
import numpy as np
import pytest
from conftest import REPO_ROOT, run_python

import data

REFERENCES = ["dataset_mean", "oracle_pair_median", "sfm_flow"]
ORACLE_ROW = "| oracle_pair_median — per-pair oracle constant (sees the truth) |"
SFM_ROW = "| sfm_flow — classical pipeline on the same flow (no training) |"


def _run_compare(data_dir, workdir, *flags):
    """Runs `experiments.compare` on gld_scenes/tiny with true flow; asserts it succeeds."""
    command = [
        sys.executable,
        "-m",
        "experiments.compare",
        "--dataset=gld_scenes/tiny",
        f"--data_dir={data_dir}",
        f"--workdir={workdir}",
        "--flow_source=gt",
        *flags,
    ]
    env = dict(os.environ, JAX_PLATFORMS="cpu", PYTHONPATH=str(REPO_ROOT))
    result = subprocess.run(
        command, capture_output=True, text=True, env=env, cwd=REPO_ROOT, timeout=600
    )
    assert result.returncode == 0, result.stderr[-3000:]
    return result


# Slow: the launcher trains and scores two models end to end; the default run keeps its
# margin under 10 minutes (experiments.paper's test covers reusing finished runs, and the
# next test runs this launcher end to end).
@pytest.mark.slow
def test_compare_writes_table_and_reuses_finished_runs(tiny_scenes_dir, tmp_path):
    workdir = tmp_path / "compare"
    flags = [
        "--models=small_encdec",
        "--classical=dataset_mean,triangulation_gt_pose,sfm_flow",
        "--steps=2",
        "--batch_size=4",
        "--checkpoint_every=2",
        "--log_every=1",
    ]

    def launch(*extra):
        return _run_compare(tiny_scenes_dir, workdir, *flags, *extra)

    first = launch()
    assert "small_encdec: training 2 steps" in first.stdout
    table = (workdir / "compare" / "table.md").read_text()
    for row in ("small_encdec", "dataset_mean", "triangulation_gt_pose"):
        assert f"| {row} |" in table
    # The references are labelled as such, listed or not.
    assert ORACLE_ROW in table and SFM_ROW in table
    assert "Abs-Inv ÷ dataset_mean" in table
    assert "Abs-Inv" in table and "protocol:" in table and "2 steps at batch 4" in table
    assert "| small_encdec | 384,367 | 2 |" in table

    results = json.loads((workdir / "compare" / "results.json").read_text())
    methods = results["methods"]
    num_test = methods["dataset_mean"]["abs_inv"]["count"]
    assert num_test == 16
    # Every method is averaged over the same examples; failed SfM pairs stay in the mean.
    for name, summary in methods.items():
        assert summary["abs_inv"]["count"] == num_test, name
    assert methods["sfm_flow"]["failed"]["count"] == num_test
    assert 0 <= results["runs"]["sfm_flow"]["failed_pairs"] <= num_test
    # With exact flow and pose, triangulation is far better than the dataset mean.
    triangulation = methods["triangulation_gt_pose"]["abs_inv"]["mean"]
    assert triangulation < 0.1 * methods["dataset_mean"]["abs_inv"]["mean"]
    # The best constant of each pair beats the one constant of every pair.
    assert (
        methods["oracle_pair_median"]["abs_inv"]["mean"]
        < methods["dataset_mean"]["abs_inv"]["mean"]
    )
    assert results["abs_inv_vs_dataset_mean"]["triangulation_gt_pose"] < 0.1

    # Re-running reuses the finished run (the classical rows are left out to save time,
    # the references stay).
    second = launch("--classical=")
    assert "small_encdec: reusing the finished run" in second.stdout
    again = json.loads((workdir / "compare" / "results.json").read_text())
    assert again["methods"]["small_encdec"] == methods["small_encdec"]
    assert list(again["methods"]) == ["small_encdec", *REFERENCES]
    assert (
        "| small_encdec | 384,367 | 2 | reused |" in (workdir / "compare" / "table.md").read_text()
    )


def test_compare_carries_the_references_whatever_it_is_asked(tiny_scenes_dir, tmp_path):
    # No learned model: nothing is trained, only the methods are evaluated.
    workdir = tmp_path / "compare"
    _run_compare(tiny_scenes_dir, workdir, "--models=", "--classical=triangulation_gt_pose")
    results = json.loads((workdir / "compare" / "results.json").read_text())
    methods = results["methods"]
    assert list(methods) == [*REFERENCES, "triangulation_gt_pose"]
    assert results["labels"] == {
        "oracle_pair_median": "per-pair oracle constant (sees the truth)",
        "sfm_flow": "classical pipeline on the same flow (no training)",
    }
    # Every reference is scored on the same examples; the classical pipeline says how
    # many pairs it failed on, and they stay in its mean.
    for name, summary in methods.items():
        assert summary["abs_inv"]["count"] == 16, name
    assert methods["sfm_flow"]["failed"]["count"] == 16
    ratios = results["abs_inv_vs_dataset_mean"]
    mean = methods["dataset_mean"]["abs_inv"]["mean"]
    for name, summary in methods.items():
        assert ratios[name] == pytest.approx(summary["abs_inv"]["mean"] / mean), name
    assert ratios["oracle_pair_median"] < 1.0

    lines = (workdir / "compare" / "table.md").read_text().splitlines()
    assert lines[0].endswith("| Abs-Inv ÷ dataset_mean |")
    assert lines[2].startswith("| dataset_mean |") and lines[2].endswith("| 1.00× |")
    assert lines[3].startswith(ORACLE_ROW)
    assert lines[3].endswith(f"| {ratios['oracle_pair_median']:.2f}× |")
    assert lines[4].startswith(SFM_ROW) and lines[4].endswith(f"| {ratios['sfm_flow']:.2f}× |")
    # The runs table names the references the same way.
    assert f"{ORACLE_ROW} 0 | 0 | none | — |" in lines
    failed = results["runs"]["sfm_flow"]["failed_pairs"]
    assert f"{SFM_ROW} 0 | 0 | none | {failed} |" in lines


@pytest.mark.slow
def test_compare_scores_a_demon_dataset_by_demons_protocol_or_stops_before_training(tmp_path):
    sys.path.insert(0, str(REPO_ROOT / "tests" / "data"))
    import demon_files

    manual_dir, data_dir = tmp_path / "manual", tmp_path / "data"
    manual_dir.mkdir()
    rng = np.random.default_rng(0)
    for split in ("train", "test"):
        with h5py.File(manual_dir / f"custom_{split}.h5", "w") as h5_file:
            for scene in ("a", "b"):
                demon_files.write_scene(h5_file, scene, demon_files.moving_views(rng, 2, 48, 64))
    data.prepare("demon/custom", data_dir, manual_dir)
    workdir = tmp_path / "compare"
    command = [
        sys.executable,
        "-m",
        "experiments.compare",
        "--dataset=demon/custom",
        f"--data_dir={data_dir}",
        f"--workdir={workdir}",
        "--classical=",
        "--steps=2",
        "--batch_size=2",
    ]
    env = dict(os.environ, JAX_PLATFORMS="cpu", PYTHONPATH=str(REPO_ROOT))

    def compare(*flags):
        return subprocess.run(
            [*command, *flags], capture_output=True, text=True, env=env, cwd=REPO_ROOT, timeout=600
        )

    # The files where the build found them: DeMoN's protocol, the files' 64x48 depth.
    scored = compare("--models=")
    assert scored.returncode == 0, scored.stderr[-3000:]
    results = json.loads((workdir / "compare" / "results.json").read_text())
    assert results["truth_resolution"] == "file" and results["truth_resolutions"] == {"64x48": 2}
    assert results["records_protocol"]["depth_resampling"] == "demon"
    assert "ground truth at the source files' resolution (2 at 64x48)" in results["protocol"]
    assert results["methods"]["oracle_pair_median"]["abs_inv"]["count"] == 2

    # Elsewhere: refused, naming both ways on, before anything is trained.
    manual_dir.rename(tmp_path / "elsewhere")
    refused = compare("--models=small_encdec", f"--workdir={tmp_path / 'refused'}")
    assert refused.returncode != 0
    assert (
        "demon/custom/2.0.0 is scored as DeMoN scores it, against the depth of the files its "
        "test split was built from (--truth_resolution=file, the default for demon/* "
        "datasets), and they are not at hand: " in refused.stderr
    )
    assert (
        "Give --manual_dir=<the folder of those files>, or --truth_resolution=record to score "
        "at the records' 256x192 (not DeMoN's protocol)" in refused.stderr
    )
    assert not (tmp_path / "refused").exists()  # nothing trained


def test_compare_flagfiles_parse_with_the_compare_flags():
    # A fresh interpreter: the compare launcher's flags share names with the trainer's.
    script = (
        "import sys; from absl import flags; import experiments.compare; "
        "import data; FLAGS = flags.FLAGS\n"
        "for path in sys.argv[1:]:\n"
        "    FLAGS(['compare', '--flagfile=' + path]); data.parse_name(FLAGS.dataset)\n"
        "    assert FLAGS.workdir.startswith('runs/compare_'), FLAGS.workdir\n"
        "    assert FLAGS.models == experiments.compare.LEARNED_DEFAULT\n"
        "    FLAGS.unparse_flags()\n"
    )
    paths = sorted(str(p) for p in (REPO_ROOT / "experiments" / "flags").glob("compare_*.flags"))
    assert len(paths) >= 3
    run_python(script, *paths, timeout=120)
