"""A recording's prediction run (gld/inference/recording_run.py): every argument is checked
against the files it names and the workdir's model, by its flag's name, before the model
is loaded or a file is written; the trajectory's poses go to their frames."""

import re

import cv2
import numpy as np
import pytest
from conftest import TINY_MODEL, tiny_train_config

from data.demon import recordings
from gld.arguments import ArgumentError
from gld.inference import recording_run
from gld.runs import workdir as workdir_lib


def _workdir(tmp_path, **model_config):
    workdir = tmp_path / "run"
    workdir_lib.write_run_config(
        workdir, tiny_train_config(model_config={**TINY_MODEL, **model_config})
    )
    return workdir


def _frames(tmp_path, count=3):
    folder = tmp_path / "frames"
    folder.mkdir()
    rng = np.random.default_rng(0)
    for index in range(count):
        cv2.imwrite(str(folder / f"frame_{index}.png"), rng.integers(0, 256, (24, 32, 3), np.uint8))
    return folder


def _trajectory(path, translations):
    """A TUM trajectory: one identity-rotation pose per translation, at t = 0, 1, 2, ..."""
    lines = [f"{t} {x} {y} {z} 0 0 0 1" for t, (x, y, z) in enumerate(translations)]
    path.write_text("\n".join(lines) + "\n")
    return path


def test_bad_arguments_are_named_before_anything_is_written(tmp_path):
    workdir, frames = _workdir(tmp_path), _frames(tmp_path)
    pairs = tmp_path / "pairs.txt"
    pairs.write_text("frame_0 frame_9\n")
    poses = _trajectory(tmp_path / "poses.txt", [(0, 0, 0), (1, 0, 0)])
    out = tmp_path / "out"
    cases = [
        ({"images": str(frames), "intrinsics": "1,2,3"}, "--intrinsics: .*expected 4"),
        ({"images": str(frames), "workdir": tmp_path / "missing"}, "--workdir: .*missing"),
        ({"images": str(frames), "video": "rec.mp4"}, "give exactly one of --images"),
        ({}, "give exactly one of --images"),
        ({"images": str(tmp_path / "none")}, "--images: image folder .*none does not exist"),
        ({"video": str(tmp_path / "none.mp4")}, "--video: "),
        ({"images": str(frames), "pairs": str(pairs)}, "--pairs: .*frame_9"),
        ({"images": str(frames), "poses": str(poses)}, "--poses: 3 images but 2 poses"),
    ]
    for arguments, message in cases:
        arguments = {"workdir": workdir, **arguments}
        with pytest.raises(ArgumentError, match=message):
            recording_run.predict_recording_run(
                arguments.pop("workdir"), out, files=recordings, **arguments
            )
        assert not out.exists(), arguments


def test_a_model_given_the_pose_or_the_camera_needs_them(tmp_path):
    frames = _frames(tmp_path)
    out = tmp_path / "out"
    given_pose = _workdir(tmp_path / "pose", global_source="pose")
    with pytest.raises(ArgumentError, match="--poses: the model was trained given the relative"):
        recording_run.predict_recording_run(given_pose, out, files=recordings, images=str(frames))
    flow_pose = _workdir(tmp_path / "flow_pose", global_source="flow_pose")
    with pytest.raises(ArgumentError, match="--intrinsics: the model takes the camera motion"):
        recording_run.predict_recording_run(flow_pose, out, files=recordings, images=str(frames))
    assert not out.exists()


def test_camera_poses_go_to_frames_by_order_or_by_time(tmp_path):
    translations = [(0, 0, 0), (1, 0, 0), (3, 0, 0)]
    poses = _trajectory(tmp_path / "poses.txt", translations)
    by_order = recording_run.camera_poses(recordings, poses, None, ["a", "b", "c"], 0.02)
    assert by_order.shape == (3, 4, 4)
    np.testing.assert_allclose(by_order[:, :3, 3], translations)
    # Images named by time stamp take the nearest pose in time.
    paths = [tmp_path / f"{stamp}.png" for stamp in ("2.0", "0.01")]
    by_time = recording_run.camera_poses(recordings, poses, paths, ["2.0", "0.01"], 0.02)
    np.testing.assert_allclose(by_time[:, :3, 3], [(3, 0, 0), (0, 0, 0)])
    with pytest.raises(ArgumentError, match=r"--max_time_difference=0.02: .*0.5.png is 0.500 s"):
        recording_run.camera_poses(recordings, poses, [tmp_path / "0.5.png"], ["0.5"], 0.02)


def test_frames_numbered_beside_stamped_poses_match_by_order(tmp_path):
    translations = [(0, 0, 0), (1, 0, 0), (3, 0, 0)]
    poses = tmp_path / "poses.txt"
    poses.write_text(
        "".join(
            f"{1305031102.1 + 0.1 * t} {x} {y} {z} 0 0 0 1\n"
            for t, (x, y, z) in enumerate(translations)
        )
    )
    names = ["000000", "000001", "000002"]
    paths = [tmp_path / f"{name}.png" for name in names]
    with pytest.raises(ArgumentError) as refused:
        recording_run.camera_poses(recordings, poses, paths, names, 0.02)
    assert re.fullmatch(
        r"--match_frames=auto: .*000000\.png is 1305031102\.100 s from the nearest pose's time "
        r"stamp: .* --match_frames=order matches the i-th image to the i-th pose",
        str(refused.value),
    ), refused.value
    by_order = recording_run.camera_poses(recordings, poses, paths, names, 0.02, "order")
    np.testing.assert_allclose(by_order[:, :3, 3], translations)


def test_match_frames_refusals_are_one_line_naming_the_flag(tmp_path):
    workdir, frames = _workdir(tmp_path), _frames(tmp_path)
    poses = _trajectory(tmp_path / "poses.txt", [(0, 0, 0), (1, 0, 0), (2, 0, 0)])
    ranges = tmp_path / "range.csv"
    ranges.write_text("frame,u,v,depth\nframe_0,1,1,2.0\nframe_2,1,1,2.0\n")
    out = tmp_path / "out"
    cases = [
        (
            {"poses": str(poses), "match_frames": "time"},
            r"--match_frames=time: .*frame_0\.png is not named by a time stamp .*"
            r"--match_frames=order matches by order",
        ),
        (
            {"ranges": str(ranges), "match_frames": "order"},
            r"--match_frames=order: 3 images but .*range\.csv has readings of 2 frames; .*",
        ),
        (
            {
                "video": str(tmp_path / "rec.mp4"),
                "images": None,
                "poses": str(poses),
                "match_frames": "time",
            },
            "--match_frames=time: a video's frames have no time stamps; .*",
        ),
    ]
    for arguments, message in cases:
        with pytest.raises(ArgumentError) as refused:
            recording_run.predict_recording_run(
                workdir, out, files=recordings, **{"images": str(frames), **arguments}
            )
        assert re.fullmatch(message, str(refused.value)), refused.value
        assert not out.exists(), arguments
    # By order the readings' frames (a, b, c: neither names nor indices) are the images:
    # the run reads them and stops only at what the model needs.
    ranges.write_text("frame,u,v,depth\na,1,1,2.0\nb,1,1,3.0\nc,2,2,4.0\n")
    with pytest.raises(ArgumentError, match="--intrinsics: the model takes the camera motion"):
        recording_run.predict_recording_run(
            _workdir(tmp_path / "flow_pose", global_source="flow_pose"),
            out,
            files=recordings,
            images=str(frames),
            ranges=str(ranges),
            match_frames="order",
        )


def test_a_model_reading_its_given_odometry_against_the_flow_needs_poses_and_camera(tmp_path):
    """A model given the odometry that derotates and triangulates the flow under it reads
    the pose and the cameras: a run needs --poses and --intrinsics, each named."""
    frames = _frames(tmp_path)
    poses = _trajectory(tmp_path / "poses.txt", [(0, 0, 0), (1, 0, 0), (3, 0, 0)])
    out = tmp_path / "out"
    workdir = _workdir(tmp_path, global_source="pose", derotate_flow=True, parallax_depth=True)
    with pytest.raises(ArgumentError, match="--poses: the model was trained given the relative"):
        recording_run.predict_recording_run(
            workdir, out, files=recordings, images=str(frames), intrinsics="30,30,15.5,11.5"
        )
    with pytest.raises(ArgumentError, match="--intrinsics: the model takes the camera motion"):
        recording_run.predict_recording_run(
            workdir, out, files=recordings, images=str(frames), poses=str(poses)
        )
    assert not out.exists()
