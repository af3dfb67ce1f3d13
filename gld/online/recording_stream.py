"""A robot's recording as a stream of frames (`gld.online.stream.FrameStream`).

    stream = open_recording(recording_files, images="rec/rgb", poses="rec/poses.txt",
                            ranges="rec/range.csv", intrinsics="517.3,516.5,318.6,255.3",
                            frame_rate=10.0, height=96, width=128)

The recording is what `experiments.predict` reads (`gld.inference.recording_run`): an
image folder or a video, a TUM trajectory as the odometry, the range CSV
(`frame,u,v,depth`) and the camera. Frames are read one at a time and resized by area to
the learner's resolution (`gld.inference.resampling`), the camera and the readings'
pixels with them. A frame's reading is its first one in the CSV (the robot's sensor
measures one point); a frame without one has none (and counts in `describe()`); a
malformed row, an unknown frame or a pixel outside the image is refused by the reader,
naming the file and line. There is no truth, so such a stream is not scored.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from gld import geometry
from gld.arguments import ArgumentError
from gld.inference import frames as frames_lib
from gld.inference import recording_run, recordings, resampling
from gld.inference.inputs import resize_camera_matrix
from gld.online.stream import Frame


class RecordingStream:
    """A recording's frames with odometry and range readings, at the learner's size."""

    def __init__(
        self,
        frames: frames_lib.CachedFrames,
        camera_to_world: np.ndarray,
        readings: dict[int, np.ndarray],
        camera_matrix: np.ndarray,
        frame_rate: float,
        height: int,
        width: int,
    ):
        if len(camera_to_world) != len(frames):
            raise ValueError(f"{len(camera_to_world)} poses for {len(frames)} frames")
        if not frame_rate > 0:
            raise ValueError(f"frame_rate must be > 0, got {frame_rate}")
        self.height, self.width, self.length = height, width, len(frames)
        self._frames, self._frame_rate = frames, frame_rate
        self._camera_to_world = np.asarray(camera_to_world, np.float64)
        in_height, in_width = frames.read(0).shape[:2]
        self._box = (0, 0, in_height, in_width)
        camera = resize_camera_matrix(np.asarray(camera_matrix), self._box, height, width)
        self._intrinsics = np.asarray(
            geometry.normalised_intrinsics(camera, height, width), np.float32
        )
        scale = np.array([width / in_width, height / in_height])
        # One reading a frame, its pixel moved to the resized frame (pixel centres).
        self._readings = {
            index: (*((values[0, :2] + 0.5) * scale - 0.5), float(values[0, 2]))
            for index, values in readings.items()
            if len(values)
        }
        self.without_reading = [
            frames.names[i] for i in range(len(frames)) if i not in self._readings
        ]

    def frames(self, start: int = 0) -> Iterator[Frame]:
        """The frames from `start` on, resized, with their odometry and reading."""
        for index in range(start, self.length):
            image = self._frames.read(index)
            if image.ndim == 2:
                image = np.repeat(image[..., None], 3, axis=-1)
            unit = image[None, ..., :3].astype(np.float32) / 255.0
            resized = resampling.model_frames(unit, self._box, self.height, self.width)[0]
            world_to_camera = np.linalg.inv(self._camera_to_world[index])
            yield Frame(
                index=index,
                time=index / self._frame_rate,
                image=np.clip(resized * 255.0 + 0.5, 0, 255).astype(np.uint8),
                rotation=world_to_camera[:3, :3],
                translation=world_to_camera[:3, 3],
                intrinsics=self._intrinsics,
                reading=self._readings.get(index),
            )

    def describe(self) -> dict[str, Any]:
        """The recording: frames, readings, those without one (the first 10 named)."""
        return {
            "source": "recording",
            "frames": self.length,
            "frame_rate": self._frame_rate,
            "size": [self.height, self.width],
            "frames_with_reading": len(self._readings),
            "frames_without_reading": len(self.without_reading),
            "without_reading_first": self.without_reading[:10],
        }


def open_recording(
    files: recording_run.RecordingFiles,
    *,
    images: str | None,
    video: str | None,
    poses: str | None,
    ranges: str | None,
    range_scale: float,
    intrinsics: str | None,
    frame_rate: float,
    height: int,
    width: int,
    match_frames: str = "auto",
    max_time_difference: float = 0.02,
) -> RecordingStream:
    """The stream of a recording's files (`files`: the data layer's readers); a bad or
    missing file is refused by the flag that names it. `match_frames` finds the frame of
    a pose and a reading as `experiments.predict` does (auto, time or order)."""
    for name, value in (("poses", poses), ("ranges", ranges), ("intrinsics", intrinsics)):
        if not value:
            raise ArgumentError(f"--{name} is needed: the learner takes a recording's {name}")
    frames, image_paths = recording_run.open_frames(files, images=images, video=video, cache_size=2)
    first = frames.read(0)
    try:
        camera_matrix = files.read_intrinsics(intrinsics)
    except ValueError as error:
        raise ArgumentError(f"--intrinsics: {error}") from None
    files.check_match_frames(match_frames)
    camera_to_world = recording_run.camera_poses(
        files, poses, image_paths, frames.names, max_time_difference, match_frames
    )
    ranges_path = Path(ranges).expanduser()
    frame_paths = list(image_paths) if image_paths else [Path(name) for name in frames.names]
    try:
        readings = recordings.read_range_readings(
            ranges_path,
            frames.names,
            first.shape[:2],
            range_scale,
            frame_indices=lambda fields, line_numbers: files.reading_frame_indices(
                fields, line_numbers, ranges_path, frame_paths, match_frames, max_time_difference
            ),
        )
    except ArgumentError:
        raise
    except (FileNotFoundError, ValueError, OSError) as error:
        raise ArgumentError(f"--ranges: {error}") from None
    return RecordingStream(
        frames, camera_to_world, readings, camera_matrix, frame_rate, height, width
    )
