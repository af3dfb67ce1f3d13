"""`python -m experiments.paper` on the tiny benchmark: runs, analyses and report; a
finished task is reused; a killed suite continues where it stopped."""

import json
import os
import shutil
import signal
import subprocess
import sys
import time

import pytest
from conftest import REPO_ROOT

from gld.paper import suite as paper_suite
from gld.paper.scales import SUITES

ENV = dict(os.environ, JAX_PLATFORMS="cpu", PYTHONPATH=str(REPO_ROOT))
RUNS = len(paper_suite.suite_runs(SUITES["tiny"]))


def _command(data_dir, workdir, report_dir, only):
    return [
        sys.executable,
        "-m",
        "experiments.paper",
        "--suite=tiny",
        f"--data_dir={data_dir}",
        f"--workdir={workdir}",
        f"--report_dir={report_dir}",
        f"--only={only}",
        "--noprogress",
    ]


def _run(*args):
    result = subprocess.run(
        _command(*args), capture_output=True, text=True, env=ENV, cwd=REPO_ROOT, timeout=900
    )
    assert result.returncode == 0, result.stderr[-3000:]
    return result.stdout


@pytest.mark.slow  # the whole suite; each task once
def test_suite_killed_continues_reports_reuses_and_finishes(tiny_scenes_dir, tmp_path):
    """A suite killed after its first task continues where it stopped and reports what is
    finished; an analysis retrains a run whose checkpoint is gone; then the whole suite,
    DispNet, FCRN and the flow experiment included, finishes on the tasks already done."""
    workdir, report_dir = tmp_path / "suite", tmp_path / "report"
    results = report_dir / "results"
    # First the analyses that need no other run.
    only = "train/global_local_1px,train/global_local_no_epipolar,classical/tiny,filters"
    # Killed (the whole process group) once its first task has finished.
    process = subprocess.Popen(
        _command(tiny_scenes_dir, workdir, report_dir, only),
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        env=ENV,
        cwd=REPO_ROOT,
        start_new_session=True,
    )
    first_result = results / "train__global_local_1px.json"
    deadline = time.monotonic() + 600
    while not first_result.exists() and process.poll() is None and time.monotonic() < deadline:
        time.sleep(0.2)
    os.killpg(process.pid, signal.SIGKILL)
    process.wait()
    assert first_result.exists()
    assert not (report_dir / "README.md").exists()
    assert any((workdir / "compile_cache").iterdir())  # what it compiled, for what follows
    stamp = first_result.stat().st_mtime_ns

    resumed = _run(tiny_scenes_dir, workdir, report_dir, only)
    assert "train/global_local_1px: done (reused" in resumed
    assert "global_local_1px: training" not in resumed
    assert first_result.stat().st_mtime_ns == stamp
    assert "global_local_no_epipolar: training 4 steps in" in resumed
    assert "train/global_local_no_epipolar — suite ETA" in resumed

    trained = json.loads(first_result.read_text())
    assert trained["config"]["steps"] == 4 and trained["metrics"]["abs_inv"]["count"] == 16
    # Evaluated during training for the over-fitting figure.
    assert [step for step, _ in trained["curves"]["test"]] == [2, 4]
    assert json.loads((results / "filters.json").read_text())["pairs"] == 16

    readme = (report_dir / "README.md").read_text()
    assert f"2 of {RUNS} training runs finished" in readme
    assert f"{trained['metrics']['abs_inv']['mean']:.4f} ±" in readme
    assert "| Eigen | not run yet |" in readme
    assert "## 7. Robustness to flow errors\n\nnot run yet." in readme
    for figure in ("overfitting.png", "density.png", "filters_0.png"):
        assert (report_dir / figure).exists(), figure

    # The results alone, in another place: an analysis retrains the run it reads and
    # checks that the retrained model scores the run's result exactly.
    moved = tmp_path / "elsewhere"
    shutil.copytree(report_dir, moved)
    (moved / "results" / "filters.json").unlink()
    continued = _run(tiny_scenes_dir, tmp_path / "fresh", moved, only)
    assert "train/global_local_1px: done (reused" in continued
    assert "global_local_1px: no checkpoint in" in continued
    assert "global_local_1px: retrained, scores exactly its result" in continued
    assert "global_local_no_epipolar: no checkpoint" not in continued  # filters reads one run
    assert json.loads((moved / "results" / "filters.json").read_text())["pairs"] == 16

    # The whole suite, in the same places: the finished tasks are reused.
    result = subprocess.run(
        [*_command(tiny_scenes_dir, workdir, report_dir, "train")[:-2], "--noprogress"],
        capture_output=True,
        text=True,
        env=ENV,
        cwd=REPO_ROOT,
        timeout=3000,
    )
    assert result.returncode == 0, result.stderr[-3000:]
    assert "train/global_local_no_epipolar: done (reused" in result.stdout
    assert first_result.stat().st_mtime_ns == stamp
    readme = (report_dir / "README.md").read_text()
    assert f"{RUNS} of {RUNS} training runs finished" in readme
    probe = json.loads((results / "pose_probe.json").read_text())["errors"]
    settings = {"scratch_mlp", "pretrained_mlp", "scratch_full", "pretrained_full"}
    assert settings <= set(probe["global_local_1px"])
    assert {"pretrained_mlp", "pretrained_full"} <= set(probe["global_local_no_epipolar"])
    curves = json.loads((results / "flow_error.json").read_text())["curves"]
    assert set(curves) == {"global_local", "triangulation_gt_pose", "triangulation_predicted_pose"}
    assert sum(curves["global_local"]["count"]) == sum(curves["triangulation_gt_pose"]["count"])
    for figure in ("flow_error.png", "overfitting.png", "density.png", "qualitative.png"):
        assert (report_dir / figure).exists(), figure
    # The flow experiment: the fixed network is the one trained on the exact flow.
    flow_net = json.loads((results / "flow_net.json").read_text())["methods"]["flow_net"]
    after = json.loads((results / "flow_finetuning.json").read_text())["epe"]
    assert after["flow_net_fixed"]["epe"] == pytest.approx(flow_net["epe"], rel=1e-5)
    assert after["flow_net_finetuned"]["epe"] != pytest.approx(flow_net["epe"], rel=1e-5)
    assert "not run yet" not in readme


def test_commit_stamp_ignores_the_suites_own_outputs(tmp_path, monkeypatch):
    from experiments import common

    def git(*args):
        subprocess.run(["git", *args], cwd=tmp_path, check=True, capture_output=True)

    git("init", "-q")
    (tmp_path / "report" / "results").mkdir(parents=True)
    for name in ("code.py", "report/README.md", "report/results/task.json"):
        (tmp_path / name).write_text("0\n")
    git("add", ".")
    git("-c", "user.name=t", "-c", "user.email=t@t", "commit", "-qm", "start")
    monkeypatch.chdir(tmp_path)
    outputs = (tmp_path / "report", tmp_path / "report" / "results")
    clean = common.commit_stamp(*outputs)
    assert clean and not clean.endswith("+changes")
    # A rewritten report or a removed result is the suite's own doing: still clean.
    (tmp_path / "report" / "README.md").write_text("1\n")
    (tmp_path / "report" / "results" / "task.json").unlink()
    assert common.commit_stamp(*outputs) == clean
    # A changed source file is not.
    (tmp_path / "code.py").write_text("1\n")
    assert common.commit_stamp(*outputs) == clean + "+changes"


def test_a_discussion_with_a_number_written_by_hand_is_refused_before_any_task(tmp_path):
    from conftest import launch

    report_dir = tmp_path / "report"
    report_dir.mkdir()
    (report_dir / "discussion.md").write_text("## ablations\nIt is 12.5% worse.\n")
    result = launch(
        "experiments.paper",
        "--suite=tiny",
        f"--workdir={tmp_path / 'runs'}",
        f"--report_dir={report_dir}",
        "--noprogress",
    )
    assert result.returncode != 0
    last = result.stderr.strip().splitlines()[-1]
    assert "discussion.md: '12.5%' written by hand (## ablations)" in last, result.stderr[-2000:]
    assert "Traceback" not in result.stderr
    assert sorted(p.name for p in report_dir.iterdir()) == ["discussion.md"]
    assert not (tmp_path / "runs").exists()
