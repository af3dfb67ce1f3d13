"""A robot's experience as a stream of frames: one interface for a simulated robot and a
recording.

Each `Frame` is what the robot has at one instant: the camera image, its odometry pose
(world-to-camera, `X_cam = R X_world + t` as `gld.geometry`; odometry drifts, so poses
are trusted only between nearby frames), at most one range reading (u, v, camera-z
metres; None when the sensor returned nothing), the camera, and in simulation the truth
(depth map and true pose) that the prequential evaluation scores against.

A `FrameStream` yields its frames in order from any position (`frames(start)`), the
same frames for the same source every time: the learner checkpoints the position and
resumes a stream exactly there.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterator
from typing import Any, Protocol

import numpy as np


@dataclasses.dataclass(frozen=True)
class Frame:
    """One instant of the robot's experience.

    Attributes:
      index: position in the stream (0, 1, ...).
      time: seconds since the stream's start.
      image: [H, W, 3] uint8 RGB.
      rotation, translation: the odometry's world-to-camera pose, [3, 3] and [3] metres.
      intrinsics: [4] normalised camera, `[fx / W, fy / H, (cx + 0.5) / W, (cy + 0.5) / H]`.
      reading: (u, v, distance): a range reading at pixel (u, v) ((0, 0) the top-left
        pixel's centre), camera-z metres; None when the sensor gave none (a dropout).
      depth: [H, W] true camera-z metres (inf where nothing is hit); None outside
        simulation.
      true_rotation, true_translation: the true world-to-camera pose; None outside
        simulation.
    """

    index: int
    time: float
    image: np.ndarray
    rotation: np.ndarray
    translation: np.ndarray
    intrinsics: np.ndarray
    reading: tuple[float, float, float] | None
    depth: np.ndarray | None = None
    true_rotation: np.ndarray | None = None
    true_translation: np.ndarray | None = None

    @property
    def center(self) -> np.ndarray:
        """The odometry's camera centre in the world, metres."""
        return -self.rotation.T @ self.translation


class FrameStream(Protocol):
    """A source of frames: a simulated robot (`data.gld_scenes.robot_stream`) or a
    recording (`gld.online.recording_stream`).

    Attributes:
      height, width: the frames' size.
      length: the number of frames, or None for an endless stream.
    """

    height: int
    width: int
    length: int | None

    def frames(self, start: int = 0) -> Iterator[Frame]:
        """The frames from position `start` on, in order; the same every call."""
        ...

    def describe(self) -> dict[str, Any]:
        """What the stream is (source, seed, rates, noise), JSON-ready, for the run's record."""
        ...
