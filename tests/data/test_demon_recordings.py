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


def test_every_number_read_is_checked_naming_file_and_line(tmp_path):
    frames = [tmp_path / "frame000.png", tmp_path / "frame001.png"]
    readings = {
        "frame000,1,1,nan": "range.csv:3: NaN or infinite value",
        "frame000,inf,1,2.0": "range.csv:3: NaN or infinite value",
        "frame000,1,1,-2.0": r"range.csv:3: depth -2.0 is not > 0",
        "frame000,1,1,0": r"range.csv:3: depth 0.0 is not > 0",
    }
    for row, message in readings.items():
        (tmp_path / "range.csv").write_text(f"frame,u,v,depth\nframe001,0,0,1.5\n{row}\n")
        with pytest.raises(ValueError, match=message):
            recordings.read_sparse_depth(tmp_path / "range.csv", frames, (4, 4), 1.0)

    (tmp_path / "trajectory.txt").write_text(
        "# t tx ty tz qx qy qz qw\n1 0 0 0 0 0 0 1\n2 0 0 0 0 0 0 0\n"
    )
    with pytest.raises(ValueError, match="trajectory.txt:3: zero quaternion"):
        recordings.read_tum_trajectory(tmp_path / "trajectory.txt")

    sheared = np.eye(4)
    sheared[0, 1] = 0.5
    (tmp_path / "poses.txt").write_text(
        "\n".join(" ".join(map(str, pose.reshape(-1))) for pose in (np.eye(4), sheared))
    )
    with pytest.raises(
        ValueError, match=r"poses.txt:2: the upper-left 3x3 block is not a rotation"
    ):
        recordings.read_pose_matrices(tmp_path / "poses.txt")
    np.save(tmp_path / "poses.npy", np.stack([np.eye(4), np.eye(4) * np.nan]))
    with pytest.raises(ValueError, match=r"poses.npy\[1\]: pose contains NaN"):
        recordings.read_pose_matrices(tmp_path / "poses.npy")

    (tmp_path / "K.txt").write_text("500 0 320\n0 500 nan\n0 0 1\n")
    with pytest.raises(ValueError, match="K.txt.*need finite values"):
        recordings.read_intrinsics(str(tmp_path / "K.txt"))
    with pytest.raises(ValueError, match="principal point .* outside the 320x240 images"):
        recordings.read_intrinsics("500,500,320,240", (240, 320))
    np.testing.assert_allclose(
        recordings.read_intrinsics("500,500,159.5,119.5", (240, 320))[:2, 2], [159.5, 119.5]
    )

    depth = np.array([[1.0, np.nan], [np.inf, 0.0]], np.float32)
    np.save(tmp_path / "depth.npy", depth)
    # 0, NaN and inf are "no reading" (TUM, REP 118); a negative depth is an error.
    np.testing.assert_array_equal(
        recordings.read_dense_depth(tmp_path / "depth.npy", 2.0), [[2.0, 0.0], [0.0, 0.0]]
    )
    depth[1, 1] = -1.0
    np.save(tmp_path / "depth.npy", depth)
    with pytest.raises(
        ValueError, match=r"depth.npy: 1 negative value\(s\), e.g. -2.0 at \(u=1, v=1\)"
    ):
        recordings.read_dense_depth(tmp_path / "depth.npy", 2.0)
