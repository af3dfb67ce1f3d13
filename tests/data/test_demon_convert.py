"""Tests of the converter's command line (data/demon/convert.py), run as a program."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
from recording_files import CX, CY, FX, FY, make_recording

import data
from data.demon import reader


def _convert(tmp_path, *flags):
    command = [
        sys.executable,
        "-m",
        "data.demon.convert",
        f"--images={tmp_path / 'rec' / 'rgb'}",
        f"--poses={tmp_path / 'rec' / 'trajectory.txt'}",
        f"--intrinsics={FX},{FY},{CX},{CY}",
        f"--depth={tmp_path / 'rec' / 'depth'}",
        "--depth_scale=0.001",
        f"--output_dir={tmp_path / 'out'}",
        *flags,
    ]
    return subprocess.run(command, capture_output=True, text=True, cwd=data.__path__[0] + "/..")


def test_command_line_writes_the_file_and_keeps_it_from_bad_runs(tmp_path):
    make_recording(tmp_path / "rec", 3, np.random.default_rng(2))
    completed = _convert(tmp_path, "--recording=lab")
    assert completed.returncode == 0, completed.stderr
    assert "custom_train_lab.h5: 2 pairs (train)" in completed.stdout
    path = tmp_path / "out" / "custom_train_lab.h5"
    with reader.DemonFile(path) as demon_file:
        assert len(demon_file.groups()) == 2
    written = path.read_bytes()

    # A recording that cannot be converted as asked: one line, exit status 2.
    refused = _convert(tmp_path, "--recording=lab", "--frame_gap=2")
    assert refused.returncode == 2 and "--overwrite" in refused.stderr
    assert len(refused.stderr.splitlines()) == 1, refused.stderr
    no_pairs = _convert(tmp_path, "--recording=lab", "--frame_gap=3", "--overwrite")
    assert no_pairs.returncode == 2 and "3 frames give no train pairs" in no_pairs.stderr
    assert len(no_pairs.stderr.splitlines()) == 1, no_pairs.stderr
    assert path.read_bytes() == written
    assert [file.name for file in (tmp_path / "out").iterdir()] == [path.name]

    replaced = _convert(tmp_path, "--recording=lab", "--frame_gap=2", "--overwrite")
    assert replaced.returncode == 0, replaced.stderr
    assert "custom_train_lab.h5: 1 pairs (train)" in replaced.stdout
