"""The online launcher (python -m experiments.online) killed with SIGKILL and relaunched."""

import json
import os
import signal
import subprocess
import sys
import time

import pytest
from conftest import REPO_ROOT, launch

# A tiny stream and learner: 24x32 frames, 30 frames, a checkpoint every 10.
COMMON = [
    "--size=24x32",
    "--frames=30",
    "--checkpoint_every=10",
    "--window=10",
    "--min_baseline=0.04",
    "--max_partner_gap=6",
    "--batch_size=2",
    "--capacity=16",
    "--noprogress",
]


def _rows(workdir):
    lines = (workdir / "prequential.jsonl").read_text().splitlines()
    return [
        {key: value for key, value in json.loads(line).items() if not key.endswith("_ms")}
        for line in lines
    ]


@pytest.mark.slow
def test_a_run_killed_part_way_resumes_and_ends_as_an_uninterrupted_one(tmp_path):
    killed = tmp_path / "killed"
    process = subprocess.Popen(
        [sys.executable, "-m", "experiments.online", f"--workdir={killed}", *COMMON],
        env=dict(os.environ, JAX_PLATFORMS="cpu", PYTHONPATH=str(REPO_ROOT)),
        cwd=REPO_ROOT,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    checkpoints = killed / "checkpoints"
    deadline = time.time() + 300
    while time.time() < deadline and process.poll() is None:
        if checkpoints.exists() and any(path.name == "10" for path in checkpoints.iterdir()):
            break
        time.sleep(0.05)
    process.send_signal(signal.SIGKILL)
    process.wait()
    saved = [int(path.name) for path in checkpoints.iterdir() if path.name.isdigit()]
    assert saved and max(saved) < 30, "the run was not interrupted part-way"

    resumed = launch("experiments.online", f"--workdir={killed}", *COMMON, timeout=600)
    assert resumed.returncode == 0, resumed.stderr[-3000:]
    straight = launch(
        "experiments.online", f"--workdir={tmp_path / 'straight'}", *COMMON, timeout=600
    )
    assert straight.returncode == 0, straight.stderr[-3000:]
    # No frame lost or scored twice, and every score as the uninterrupted run's.
    assert [row["frame"] for row in _rows(killed)] == list(range(30))
    assert _rows(killed) == _rows(tmp_path / "straight")


@pytest.mark.parametrize(
    "flag, message",
    [
        ("--reading_pixel=64", "--reading_pixel must be two integers u,v, got 64"),
        ("--reading_pixel=a,b", "--reading_pixel must be two integers u,v, got a,b"),
        ("--reading_pixel=40,3", "reading_pixel must lie in the 32x24 image"),
        ("--teacher_parallax=0", "teacher_parallax > 0, got 0 and 0.0"),
        ("--teacher_labels=-1", "-1 is not a non-negative integer"),
        ("--cpu_devices=0", "flag --cpu_devices=0: 0 is not a positive integer"),
    ],
)
def test_a_bad_flag_is_refused_in_one_line_before_anything_is_written(tmp_path, flag, message):
    workdir = tmp_path / "run"
    completed = launch("experiments.online", f"--workdir={workdir}", flag, *COMMON)
    assert completed.returncode == 2, completed.stderr[-2000:]
    assert message in completed.stderr and "Traceback" not in completed.stderr
    assert len(completed.stderr.strip().splitlines()) == 1
    assert not workdir.exists()


@pytest.mark.parametrize(
    "flag, message",
    [
        ("--camera_yaw=90", "--camera_yaw sets the simulated robot"),
        ("--references", "--references scores against the simulator's truth"),
    ],
)
def test_a_simulator_flag_with_a_recording_is_refused(tmp_path, flag, message):
    workdir = tmp_path / "run"
    completed = launch(
        "experiments.online", f"--workdir={workdir}", f"--images={tmp_path}", flag, *COMMON
    )
    assert completed.returncode == 2, completed.stderr[-2000:]
    assert message in completed.stderr
    assert len(completed.stderr.strip().splitlines()) == 1 and not workdir.exists()
