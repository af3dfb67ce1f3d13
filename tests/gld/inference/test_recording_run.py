"""A recording's prediction run (gld/inference/recording_run.py): every argument is checked
against the files it names and the workdir's model, by its flag's name, before the model
is loaded or a file is written; the trajectory's poses go to their frames."""

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
    with pytest.raises(ArgumentError, match="--poses: .*max_time_difference"):
        recording_run.camera_poses(recordings, poses, [tmp_path / "0.5.png"], ["0.5"], 0.02)
