"""Tests of the simulated robot's frame stream (data/gld_scenes/robot_stream.py), tiny renders."""

import dataclasses
import itertools
import json

import numpy as np
import pytest

from data.gld_scenes import robot_stream, scenes
from gld import geometry

SETTINGS = robot_stream.RobotSettings(height=48, width=64)


def _take(stream, count, start=0):
    return list(itertools.islice(stream.frames(start), count))


def _assert_same_frames(frames_a, frames_b):
    assert len(frames_a) == len(frames_b)
    for a, b in zip(frames_a, frames_b, strict=True):
        assert a.index == b.index and a.time == b.time and a.reading == b.reading
        for name in ("image", "depth", "rotation", "translation", "true_rotation"):
            np.testing.assert_array_equal(getattr(a, name), getattr(b, name))


def _relative_errors(frames):
    """Per consecutive pair: (rotation error degrees, translation error / step length) of
    the odometry's relative pose against the true one."""
    rotation_errors, translation_errors = [], []
    for previous, frame in itertools.pairwise(frames):
        odometry = geometry.relative_pose(
            previous.rotation, previous.translation, frame.rotation, frame.translation
        )
        truth = geometry.relative_pose(
            previous.true_rotation,
            previous.true_translation,
            frame.true_rotation,
            frame.true_translation,
        )
        rotation_errors.append(geometry.rotation_error_degrees(odometry[0], truth[0]))
        step = np.linalg.norm(truth[1])
        translation_errors.append(np.linalg.norm(odometry[1] - truth[1]) / step)
    return np.array(rotation_errors), np.array(translation_errors)


def test_frames_are_a_function_of_the_seed():
    frames = _take(robot_stream.SimulatedRobot(3, SETTINGS), 4)
    _assert_same_frames(frames, _take(robot_stream.SimulatedRobot(3, SETTINGS), 4))
    other = _take(robot_stream.SimulatedRobot(4, SETTINGS), 4)
    assert not np.array_equal(frames[0].image, other[0].image)
    assert not np.allclose(frames[0].true_translation, other[0].true_translation)


def test_frames_from_start_are_the_frames_from_zero_from_there_on():
    robot = robot_stream.SimulatedRobot(0, dataclasses.replace(SETTINGS, length=7))
    frames = list(robot.frames())
    assert [frame.index for frame in frames] == list(range(7))
    _assert_same_frames(list(robot.frames(start=4)), frames[4:])
    assert list(robot.frames(start=7)) == []


def test_frame_fields():
    settings = dataclasses.replace(SETTINGS, frame_rate=5.0)
    frames = _take(robot_stream.SimulatedRobot(1, settings), 3)
    for frame in frames:
        assert frame.image.shape == (48, 64, 3) and frame.image.dtype == np.uint8
        assert frame.depth.shape == (48, 64) and frame.depth.dtype == np.float32
        assert frame.time == pytest.approx(frame.index / 5.0)
        assert frame.intrinsics.dtype == np.float32
        np.testing.assert_allclose(frame.intrinsics, scenes.NOMINAL_INTRINSICS, rtol=1e-6)
        # The odometry's camera centre is the `Frame.center` of its pose.
        np.testing.assert_allclose(frame.center, -frame.rotation.T @ frame.translation)
    # Odometry starts at the true pose.
    np.testing.assert_array_equal(frames[0].rotation, frames[0].true_rotation)
    np.testing.assert_array_equal(frames[0].translation, frames[0].true_translation)


@pytest.mark.parametrize("world", ["training", "shifted"])
def test_motion_is_continuous_forward_and_clear_of_walls_and_objects(world):
    settings = dataclasses.replace(SETTINGS, world=world)
    robot = robot_stream.SimulatedRobot(2, settings)
    poses = list(itertools.islice(robot.true_poses(), 1500))  # 150 s
    centers = np.array([-rotation.T @ translation for rotation, translation in poses])
    steps = np.diff(centers, axis=0)
    lengths = np.linalg.norm(steps, axis=-1)
    step_time = 1.0 / settings.frame_rate
    # Speed is clipped to 2x the mean (plus the height oscillation's few millimetres).
    assert lengths.max() <= 2 * settings.mean_speed * step_time + 0.005
    assert 0.6 * settings.mean_speed < lengths.mean() / step_time < 1.2 * settings.mean_speed
    angles = [
        geometry.rotation_angle_degrees(geometry.relative_pose(*a, *b)[0])
        for a, b in itertools.pairwise(poses)
    ]
    assert max(angles) < 8.0  # at most 60 deg/s of turn, plus the pitch's oscillation
    # The camera looks along its motion: its heading is the step's horizontal direction.
    forward = np.array([rotation[2] for rotation, _ in poses[1:]])[:, [0, 2]]
    direction = steps[:, [0, 2]] / np.linalg.norm(steps[:, [0, 2]], axis=-1, keepdims=True)
    cosines = np.sum(direction * forward, -1) / np.linalg.norm(forward, axis=-1)
    assert cosines.min() > 0.999
    # Inside the room by the wall margin, outside every object by the object margin.
    room = robot.scene.room_size
    horizontal = centers[:, [0, 2]]
    assert np.all(horizontal >= settings.wall_margin - 1e-6)
    assert np.all(horizontal <= room[[0, 2]] - settings.wall_margin + 1e-6)
    assert np.all((centers[:, 1] > 0.5) & (centers[:, 1] < room[1]))
    for obj in robot.scene.objects:
        distance = np.linalg.norm(centers - obj.center, axis=-1)
        assert distance.min() >= obj.bounding_radius + settings.object_margin - 1e-6
    # It wanders the room rather than circling in one place: 0.5 m cells visited.
    assert len({tuple(cell) for cell in (horizontal // 0.5).astype(int)}) > 40


def test_odometry_errors_match_the_stated_noise():
    settings = robot_stream.RobotSettings(
        height=8,
        width=8,
        odometry_translation_noise=0.05,
        odometry_rotation_noise_degrees=0.3,
    )
    frames = _take(robot_stream.SimulatedRobot(5, settings), 201)
    rotation_errors, translation_errors = _relative_errors(frames)
    # The norm of a 3-D gaussian of deviation sigma per axis has mean sqrt(8 / pi) sigma.
    expected = np.sqrt(8 / np.pi)
    assert rotation_errors.mean() / 0.3 == pytest.approx(expected, rel=0.15)
    assert translation_errors.mean() / 0.05 == pytest.approx(expected, rel=0.15)
    # Integrated, the errors drift: the last odometry centre is off the true one.
    last = frames[-1]
    true_center = -last.true_rotation.T @ last.true_translation
    assert np.linalg.norm(last.center - true_center) > 0.01


def test_odometry_without_noise_is_the_truth():
    settings = dataclasses.replace(
        SETTINGS, height=8, width=8, odometry_translation_noise=0, odometry_rotation_noise_degrees=0
    )
    frames = _take(robot_stream.SimulatedRobot(5, settings), 40)
    rotation_errors, translation_errors = _relative_errors(frames)
    assert rotation_errors.max() < 1e-4 and translation_errors.max() < 1e-9
    np.testing.assert_allclose(frames[-1].rotation, frames[-1].true_rotation, atol=1e-9)
    np.testing.assert_allclose(frames[-1].translation, frames[-1].true_translation, atol=1e-9)


def test_range_readings_are_the_depth_with_the_stated_noise_and_dropout():
    settings = robot_stream.RobotSettings(height=8, width=10, range_noise=0.02, range_dropout=0.2)
    frames = _take(robot_stream.SimulatedRobot(6, settings), 500)
    readings = [frame for frame in frames if frame.reading is not None]
    assert {frame.reading[:2] for frame in readings} == {(5.0, 4.0)}  # the centre pixel
    relative = np.array([frame.reading[2] / frame.depth[4, 5] - 1.0 for frame in readings])
    assert relative.std() == pytest.approx(0.02, rel=0.1)
    assert abs(relative.mean()) < 0.003
    assert 1 - len(readings) / len(frames) == pytest.approx(0.2, abs=0.04)


def test_range_readings_at_another_pixel_and_beyond_the_range():
    settings = robot_stream.RobotSettings(
        height=8, width=8, range_noise=0, range_dropout=0, reading_pixel=(1, 6)
    )
    frames = _take(robot_stream.SimulatedRobot(6, settings), 5)
    for frame in frames:
        assert frame.reading == (1.0, 6.0, pytest.approx(float(frame.depth[6, 1])))
    near = dataclasses.replace(settings, max_range=0.3)  # nearer than any wall can be
    assert all(frame.reading is None for frame in _take(robot_stream.SimulatedRobot(6, near), 5))


def test_the_shifted_world_differs_as_documented():
    training = robot_stream.SimulatedRobot(7, SETTINGS)
    shifted = robot_stream.SimulatedRobot(7, dataclasses.replace(SETTINGS, world="shifted"))
    world = robot_stream.WORLDS["shifted"]
    np.testing.assert_allclose(shifted.intrinsics, world.intrinsics)
    assert shifted.intrinsics[0] < 0.8 * training.intrinsics[0]  # a wider view
    # The same room draw, its floor stretched, its colours tinted, its patterns coarser.
    np.testing.assert_allclose(
        shifted.scene.room_size, training.scene.room_size * np.array([1.6, 1.0, 1.6]), rtol=1e-6
    )
    for plain, changed in zip(
        training.scene.room_materials, shifted.scene.room_materials, strict=True
    ):
        np.testing.assert_allclose(changed.color_a, plain.color_a * np.array(world.tint))
        assert changed.scale == pytest.approx(2.0 * plain.scale)
    description = json.loads(json.dumps(shifted.describe()))
    assert description["world"] == "shifted" and description["seed"] == 7
    assert description["source"] == "gld_scenes robot"
    assert description["world_settings"]["room_scale"] == 1.6
    assert description["reading_pixel"] == [32, 24]


@pytest.mark.parametrize(
    "name, value",
    [
        ("height", 4),
        ("width", 7),
        ("length", -1),
        ("world", "moon"),
        ("frame_rate", 0),
        ("mean_speed", -0.1),
        ("correlation_time", 0),
        ("max_range", 0),
        ("speed_deviation", -1),
        ("odometry_translation_noise", -0.01),
        ("odometry_rotation_noise_degrees", -1),
        ("range_noise", -0.01),
        ("camera_height", 2.5),
        ("pitch_amplitude_degrees", 45),
        ("wall_margin", 2.0),
        ("range_dropout", 1.5),
        ("reading_pixel", (64, 0)),
        ("camera_yaw_degrees", 200),
    ],
)
def test_bad_settings_are_refused_by_name(name, value):
    with pytest.raises(ValueError, match=name):
        dataclasses.replace(SETTINGS, **{name: value})


@pytest.mark.parametrize("yaw, axis", [(0.0, 2), (90.0, 0)])
def test_the_camera_looks_ahead_or_sideways(yaw, axis):
    """The direction of travel in the camera's frame: along its optical axis (z) when it
    looks ahead, along its x axis when it looks sideways (same trajectory)."""
    settings = dataclasses.replace(SETTINGS, camera_yaw_degrees=yaw)
    poses = list(itertools.islice(robot_stream.SimulatedRobot(4, settings).true_poses(), 40))
    shares = []
    for (rotation1, translation1), (rotation2, translation2) in itertools.pairwise(poses):
        _, translation = geometry.relative_pose(rotation1, translation1, rotation2, translation2)
        shares.append(abs(translation[axis]) / np.linalg.norm(translation))
    assert np.median(shares) > 0.95
