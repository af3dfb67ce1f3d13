"""Tests of data/demon/recordings.py: reading a recording's poses, intrinsics, depth; pairs."""

from __future__ import annotations

import demon_files
import numpy as np
import pytest
from recording_files import quaternion_xyzw

from data.demon import recordings


def test_quaternions_follow_tum_convention():
    # 90 degrees about z maps x to y.
    rotation = recordings.quaternion_to_rotation(np.array(quaternion_xyzw([0, 0, 1], 90.0)))
    np.testing.assert_allclose(rotation @ [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], atol=1e-12)
    random_rotation = demon_files.rotation_about([0.3, -0.2, 0.9], 37.0)
    quaternion = quaternion_xyzw([0.3, -0.2, 0.9], 37.0)
    np.testing.assert_allclose(
        recordings.quaternion_to_rotation(np.array(quaternion)), random_rotation
    )


def test_pairs_by_frame_gap_and_baseline():
    centres = np.array([[0.0, 0, 0], [0.05, 0, 0], [0.12, 0, 0], [0.3, 0, 0], [0.31, 0, 0]])
    assert recordings.select_pairs(centres, frame_gap=2) == [(0, 2), (1, 3), (2, 4)]
    assert recordings.select_pairs(centres, min_baseline=0.1, max_baseline=0.2) == [(0, 2), (2, 3)]
    assert recordings.select_pairs(
        centres, min_baseline=0.1, max_baseline=0.2, max_frame_gap=1
    ) == [(2, 3)]


def test_user_mistakes_name_the_input(tmp_path):
    (tmp_path / "bad.csv").write_text("frame,u,v,depth\nframe999,1,1,2.0\n")
    with pytest.raises(ValueError, match=r"bad.csv:2: frame 'frame999'"):
        recordings.read_sparse_depth(tmp_path / "bad.csv", [tmp_path / "frame000.png"], (4, 4), 1.0)
    with pytest.raises(ValueError, match="intrinsics"):
        recordings.read_intrinsics("1,2,3")
