"""A recording as the learner's stream (gld/online/recording_stream.py), and the launcher's
refusals (experiments/online.py)."""

import itertools

import cv2
import numpy as np
import pytest
from conftest import launch
from scipy.spatial.transform import Rotation

from data.demon import recordings as recording_files
from data.gld_scenes import robot_stream
from gld.arguments import ArgumentError
from gld.online import recording_stream

SIZE = (48, 64)  # the recording's frames; the learner's: half of it


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    """A simulated robot's frames written as a recording: PNGs named by time stamp, a
    TUM trajectory of its odometry, a range CSV without a reading for frame 3; and its
    frames."""
    folder = tmp_path_factory.mktemp("recording")
    robot = robot_stream.SimulatedRobot(
        1, robot_stream.RobotSettings(height=SIZE[0], width=SIZE[1])
    )
    frames = list(itertools.islice(robot.frames(), 6))
    (folder / "rgb").mkdir()
    poses, readings = [], ["frame,u,v,depth"]
    for frame in frames:
        name = f"{frame.time:.6f}"  # named by time stamp, as TUM's recordings
        cv2.imwrite(str(folder / "rgb" / f"{name}.png"), frame.image[..., ::-1])
        camera_to_world = np.linalg.inv(
            np.vstack([np.c_[frame.rotation, frame.translation], [0, 0, 0, 1]])
        )
        quaternion = Rotation.from_matrix(camera_to_world[:3, :3]).as_quat()  # x, y, z, w
        poses.append(" ".join(map(str, [frame.time, *camera_to_world[:3, 3], *quaternion])))
        if frame.index != 3 and frame.reading is not None:
            u, v, distance = frame.reading
            readings.append(f"{name},{u},{v},{distance}")
    (folder / "poses.txt").write_text("\n".join(poses) + "\n")
    (folder / "range.csv").write_text("\n".join(readings) + "\n")
    fx, fy, cx, cy = frames[0].intrinsics * np.float32([SIZE[1], SIZE[0], SIZE[1], SIZE[0]])
    intrinsics = f"{fx},{fy},{cx - 0.5},{cy - 0.5}"
    return folder, frames, intrinsics


def _open(folder, intrinsics, **changes):
    arguments = dict(
        images=str(folder / "rgb"),
        video=None,
        poses=str(folder / "poses.txt"),
        ranges=str(folder / "range.csv"),
        range_scale=1.0,
        intrinsics=intrinsics,
        frame_rate=10.0,
        height=SIZE[0] // 2,
        width=SIZE[1] // 2,
    )
    return recording_stream.open_recording(recording_files, **{**arguments, **changes})


def test_a_recording_streams_resized_frames_with_odometry_and_readings(recording):
    folder, frames, intrinsics = recording
    stream = _open(folder, intrinsics)
    assert (stream.height, stream.width, stream.length) == (24, 32, 6)
    streamed = list(stream.frames())
    assert [frame.index for frame in streamed] == list(range(6))
    assert list(stream.frames(4))[0].index == 4
    for original, frame in zip(frames, streamed, strict=True):
        assert frame.image.shape == (24, 32, 3) and frame.depth is None
        expected = cv2.resize(original.image, (32, 24), interpolation=cv2.INTER_AREA)
        assert np.abs(frame.image.astype(int) - expected).max() <= 1
        np.testing.assert_allclose(frame.rotation, original.rotation, atol=1e-6)
        np.testing.assert_allclose(frame.translation, original.translation, atol=1e-6)
        # Normalised intrinsics do not change with the size.
        np.testing.assert_allclose(frame.intrinsics, original.intrinsics, rtol=1e-5)
        if original.index == 3 or original.reading is None:
            assert frame.reading is None
        else:
            u, v, distance = frame.reading
            # The reading's pixel centre, in the half-size frame.
            assert (u, v) == pytest.approx(
                ((original.reading[0] + 0.5) / 2 - 0.5, (original.reading[1] + 0.5) / 2 - 0.5)
            )
            assert distance == pytest.approx(original.reading[2])
    described = stream.describe()
    assert "0.300000" in described["without_reading_first"]
    assert described["frames_with_reading"] + described["frames_without_reading"] == 6


def test_a_bad_recording_is_refused_by_name(recording, tmp_path):
    folder, _, intrinsics = recording
    with pytest.raises(ArgumentError, match="--poses is needed"):
        _open(folder, intrinsics, poses=None)
    broken = tmp_path / "range.csv"
    broken.write_text("frame,u,v,depth\n000001,10,10,2.0\n000002,ten,10,2.0\n")
    with pytest.raises(ArgumentError, match=r"--ranges: .*range.csv.*3"):
        _open(folder, intrinsics, ranges=str(broken))
    with pytest.raises(ArgumentError, match="--intrinsics"):
        _open(folder, "1,2")


def test_the_launcher_refuses_a_bad_flag_in_one_line(tmp_path):
    completed = launch("experiments.online", f"--workdir={tmp_path / 'run'}", "--size=96by128")
    assert completed.returncode == 2
    assert (
        completed.stderr.strip()
        .splitlines()[-1]
        .endswith("--size: '96by128' is not HEIGHTxWIDTH of 8 or more, e.g. 96x128")
    )
    assert "Traceback" not in completed.stderr and not (tmp_path / "run").exists()
    completed = launch("experiments.online", f"--workdir={tmp_path / 'run'}", "--zoom=0")
    assert completed.returncode == 2 and "zoom must be in (0, 1], got 0.0" in completed.stderr
