"""Tests of the converter's command line (data/demon/convert.py), run as a program."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
from recording_files import CX, CY, FX, FY, make_recording

import data
from data.demon import reader


def test_command_line_writes_the_file(tmp_path):
    make_recording(tmp_path / "rec", 3, np.random.default_rng(2))
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
        "--recording=lab",
    ]
    completed = subprocess.run(
        command, capture_output=True, text=True, cwd=data.__path__[0] + "/.."
    )
    assert completed.returncode == 0, completed.stderr
    assert "custom_train_lab.h5: 2 pairs (train)" in completed.stdout
    with reader.DemonFile(tmp_path / "out" / "custom_train_lab.h5") as demon_file:
        assert len(demon_file.groups()) == 2
