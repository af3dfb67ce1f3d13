"""Tests of data/demon/recordings.py: reading a recording's poses, intrinsics, depth; pairs."""

from __future__ import annotations

import re
from pathlib import Path

import demon_files
import numpy as np
import pytest
from recording_files import quaternion_xyzw

from data.demon import recordings
from gld.arguments import ArgumentError


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


def test_a_time_stamp_is_a_plain_decimal_number():
    assert recordings.time_stamp("1305031102.175304") == 1305031102.175304
    assert recordings.time_stamp("000120") == 120.0
    # float() reads all of these ('07_1' as 71); none names a file by time.
    for name in ("07_1", "1_000", "-1", "+1", "1e5", "nan", "inf", "1.", ".5", "1.2.3", " 1", "٣"):
        assert recordings.time_stamp(name) is None, name
    # Images named 07_1, 07_2 beside stamped poses (71.0 s listed after 72.0 s) go by
    # order, not to the poses at "71" and "72" s.
    images = [Path("07_1.png"), Path("07_2.png")]
    np.testing.assert_array_equal(
        recordings.associate_poses(images, np.array([72.0, 71.0]), 2, 0.02), [0, 1]
    )


def _refusal(call, message):
    """The ArgumentError `call()` raises: one line that matches `message` from its start."""
    with pytest.raises(ArgumentError) as raised:
        call()
    assert re.match(message, str(raised.value)), str(raised.value)
    assert "\n" not in str(raised.value)
    return str(raised.value)


def test_frames_match_by_time_or_order_and_refusals_name_the_flag(tmp_path):
    stamps = np.array([1305031102.1, 1305031102.2, 1305031102.3])
    numbered = [tmp_path / f"{index:06d}.png" for index in range(3)]
    named = [tmp_path / f"frame_{index}.png" for index in range(3)]
    stamped = [tmp_path / f"{stamp:.6f}.png" for stamp in stamps[::-1]]

    np.testing.assert_array_equal(
        recordings.associate_poses(numbered, stamps, 3, 0.02, "order"), [0, 1, 2]
    )
    np.testing.assert_array_equal(
        recordings.associate_poses(stamped, stamps, 3, 0.02, "time"), [2, 1, 0]
    )
    # Frame numbers beside Unix times: by time (`auto` too) they fail, naming the file
    # and the way out.
    for match_frames in ("auto", "time"):
        _refusal(
            lambda m=match_frames: recordings.associate_poses(numbered, stamps, 3, 0.02, m),
            rf"--match_frames={match_frames}: .*000000\.png is 1305031102\.100 s from the "
            r"nearest pose's time stamp: .* look like frame numbers.* --match_frames=order "
            r"matches the i-th image to the i-th pose$",
        )
    _refusal(
        lambda: recordings.associate_poses(named, stamps, 3, 0.02, "time"),
        r"--match_frames=time: .*frame_0\.png is not named by a time stamp",
    )
    _refusal(
        lambda: recordings.associate_poses(numbered, None, 3, 0.02, "time"),
        "--match_frames=time: the poses have no time stamps",
    )
    _refusal(
        lambda: recordings.associate_poses(numbered, stamps, 2, 0.02, "order"),
        "--match_frames=order: 3 images but 2 poses",
    )
    _refusal(
        lambda: recordings.associate_poses(stamped, stamps + 0.5, 3, 0.02, "time"),
        r"--max_time_difference=0.02: .*\.png is 0\.500 s from the nearest pose's",
    )

    depth = tmp_path / "depth"
    depth.mkdir()
    for stamp in stamps:
        np.save(depth / f"{stamp + 0.01:.6f}.npy", np.ones((2, 2)))
    by_time = recordings.associate_depth_files(depth, stamped, 0.02, "time")
    assert [path.stem for path in by_time] == [f"{stamp + 0.01:.6f}" for stamp in stamps[::-1]]
    by_order = recordings.associate_depth_files(depth, numbered, 0.02, "order")
    assert by_order == sorted(depth.iterdir())
    _refusal(
        lambda: recordings.associate_depth_files(depth, numbered[:2], 0.02, "order"),
        "--match_frames=order: 2 images but 3 depth images",
    )


def test_range_readings_match_frames_by_order_or_time(tmp_path):
    path = tmp_path / "range.csv"
    path.write_text("frame,u,v,depth\n1305.10,1,1,2.0\n1305.10,2,1,3.0\n1305.20,0,0,4.0\n")
    numbered = [tmp_path / "000000.png", tmp_path / "000001.png"]
    # By order: the frames in the order the file names them are the images.
    maps = recordings.read_sparse_depth(path, numbered, (3, 3), 1.0, "order")
    np.testing.assert_array_equal(maps[0], [[0, 0, 0], [0, 2, 3], [0, 0, 0]])
    np.testing.assert_array_equal(maps[1], [[4, 0, 0], [0, 0, 0], [0, 0, 0]])
    _refusal(
        lambda: recordings.read_sparse_depth(path, [*numbered, numbered[0]], (3, 3), 1.0, "order"),
        r"--match_frames=order: 3 images but .*range.csv has readings of 2 frames",
    )
    # By time: the image nearest each reading.
    stamped = [tmp_path / "1305.199.png", tmp_path / "1305.101.png"]
    maps = recordings.read_sparse_depth(path, stamped, (3, 3), 1.0, "time")
    assert maps[1][1, 1] == 2.0 and maps[0][0, 0] == 4.0
    _refusal(
        lambda: recordings.read_sparse_depth(path, numbered, (3, 3), 1.0, "time"),
        r"--match_frames=time: .*range.csv:4: frame 1305.20 is 1304.200 s from the nearest "
        r"image's time stamp: .*--match_frames=order matches",
    )
    path.write_text("frame_0,1,1,2.0\n")
    _refusal(
        lambda: recordings.read_sparse_depth(path, stamped, (3, 3), 1.0, "time"),
        r"--match_frames=time: .*range.csv:1: frame 'frame_0' is not a time stamp",
    )
