"""A trained workdir's depth for a whole recording, every argument checked before the
model is loaded or a file is written (`python -m experiments.predict`): the frames (a
folder or a video), their pairs, the scale's measurements (range readings or a TUM
trajectory), what the workdir's model needs besides the images, the output folder (one
run per folder, `gld.inference.prediction_folder`), then
`gld.inference.recordings.predict_recording`.

The recording's files are read by the data layer's readers (`data.demon.recordings`),
which the caller gives (`RecordingFiles`): the library does not import the data layer.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, Protocol

import numpy as np
from tqdm import tqdm

from gld.arguments import ArgumentError
from gld.inference import frames as frames_lib
from gld.inference import metric_scale, prediction_folder, recordings
from gld.inference.inputs import check_image
from gld.inference.predict import DepthPredictor
from gld.models import registry
from gld.models.global_local import POSE_INPUTS
from gld.runs import workdir as workdir_lib


class RecordingFiles(Protocol):
    """The readers of a recording's files, as `data.demon.recordings` has them."""

    def list_images(self, folder: str | Path) -> list[Path]: ...

    def read_intrinsics(self, spec: str) -> np.ndarray: ...

    def read_tum_trajectory(self, path: str | Path) -> tuple[np.ndarray, np.ndarray]: ...

    def associate_poses(
        self,
        image_paths: Sequence[Path],
        timestamps: np.ndarray | None,
        num_poses: int,
        max_time_difference: float,
        match_frames: str = "auto",
    ) -> np.ndarray: ...

    def reading_frame_indices(
        self,
        frames: Sequence[str],
        line_numbers: Sequence[int],
        csv_path: Path,
        image_paths: Sequence[Path],
        match_frames: str = "auto",
        max_time_difference: float = 0.02,
    ) -> list[int]: ...

    def check_match_frames(self, match_frames: str) -> None: ...


def _argument(name: str, error: Exception) -> ArgumentError:
    return ArgumentError(f"--{name}: {error}")


def open_frames(
    files: RecordingFiles,
    *,
    images: str | None,
    video: str | None,
    cache_size: int,
) -> tuple[frames_lib.ImageFolderFrames | frames_lib.VideoFrames, list[Path] | None]:
    """The frame source of exactly one of `images` (a folder, name order) or `video`, and
    the image paths (None for a video)."""
    if bool(images) == bool(video):
        raise ArgumentError("give exactly one of --images (a folder) or --video (a file)")
    if images:
        try:
            paths = files.list_images(Path(images).expanduser())
        except FileNotFoundError as error:
            raise _argument("images", error) from None
        return frames_lib.ImageFolderFrames(paths, cache_size=cache_size), paths
    try:
        return frames_lib.VideoFrames(Path(video).expanduser(), cache_size=cache_size), None
    except (FileNotFoundError, ValueError) as error:
        raise _argument("video", error) from None


def _frame_paths(image_paths: Sequence[Path] | None, names: Sequence[str]) -> list[Path]:
    """The frames as paths for the data layer's matching: the images, or a video's names."""
    return list(image_paths) if image_paths else [Path(name) for name in names]


def camera_poses(
    files: RecordingFiles,
    poses: str | Path,
    image_paths: Sequence[Path] | None,
    names: Sequence[str],
    max_time_difference: float,
    match_frames: str = "auto",
) -> np.ndarray:
    """[F, 4, 4] camera-to-world poses of the frames from the TUM trajectory `poses`,
    matched as `match_frames` says (`data.demon.recordings.associate_poses`): `auto` by
    time when the images are named by time stamp, else the i-th pose is the i-th frame
    (always for a video's frames, which have no time stamps)."""
    try:
        timestamps, camera_to_world = files.read_tum_trajectory(Path(poses).expanduser())
        indices = files.associate_poses(
            _frame_paths(image_paths, names),
            timestamps if image_paths else None,
            len(camera_to_world),
            max_time_difference,
            match_frames,
        )
    except ArgumentError:
        raise
    except (FileNotFoundError, ValueError) as error:
        raise _argument("poses", error) from None
    return camera_to_world[indices]


def predict_recording_run(
    workdir: str | Path,
    output_dir: str | Path,
    *,
    files: RecordingFiles,
    images: str | None = None,
    video: str | None = None,
    step: int | None = None,
    frame_gap: int = 1,
    pairs: str | None = None,
    depth_format: str = "npy",
    previews: bool = False,
    preview_scale: str = "pair",
    ply: bool = False,
    intrinsics: str | None = None,
    ranges: str | None = None,
    range_scale: float = 1.0,
    range_metric: str = "camera_z",
    poses: str | None = None,
    max_time_difference: float = 0.02,
    match_frames: str = "auto",
    min_baseline: float = 0.0,
    batch_size: int = 8,
    aspect: str = "resize",
    overwrite: bool = False,
    print_fn: Callable[[str], None] = print,
) -> dict[str, Any]:
    """Predicts depth for every pair of a recording with a trained workdir.

    The arguments are `python -m experiments.predict`'s flags (its docstring says what
    each means), checked there on their own (one source of scale, a PNG only for metric
    depth, ...); here against the files they name and the workdir's model.

    Args:
      files: the readers of the recording's files (`data.demon.recordings`).
      match_frames: how poses and range readings find their frame (`auto`, `time`,
        `order`; `data.demon.recordings.MATCH_FRAMES`), as in the converter.
      overwrite: replace an earlier run in `output_dir` (only its files; without, a
        folder holding one is refused).
      print_fn: told when an earlier run is to be replaced.

    Returns:
      `recordings.predict_recording`'s summary (what summary.json holds).

    Raises:
      ArgumentError: an argument's file is missing or wrong, `output_dir` holds an earlier
        run (without `overwrite`) or another tool's file where the run writes, or the
        model needs what is not given (the relative pose from `poses`, or the camera
        from `intrinsics`); all before anything is written. A frame that cannot be read
        or predicted part way (naming it): nothing of the run is left in `output_dir`.
    """
    files.check_match_frames(match_frames)
    if match_frames == "time" and video and (ranges or poses):
        raise ArgumentError(
            "--match_frames=time: a video's frames have no time stamps; give --images named "
            "by time stamp, or --match_frames=order"
        )
    try:
        earlier = prediction_folder.check_output_dir(
            Path(output_dir).expanduser(), overwrite=overwrite
        )
    except (FileExistsError, ValueError) as error:
        raise _argument("output_dir", error) from None
    camera_matrix = None
    if intrinsics:
        try:
            camera_matrix = files.read_intrinsics(intrinsics)
        except ValueError as error:
            raise _argument("intrinsics", error) from None
    try:
        config = workdir_lib.load_run_config(workdir)
    except FileNotFoundError as error:
        raise _argument("workdir", error) from None

    frames, image_paths = open_frames(
        files, images=images, video=video, cache_size=batch_size + frame_gap + 2
    )
    try:
        first_frame = frames.read(0)
        check_image(first_frame, f"frame {frames.names[0]}")
    except ValueError as error:
        raise _argument("images" if images else "video", error) from None
    image_size = first_frame.shape[:2]
    try:
        if pairs:
            frame_pairs = recordings.read_pairs_file(Path(pairs).expanduser(), frames.names)
        else:
            frame_pairs = recordings.frame_pairs(len(frames), frame_gap)
    except (FileNotFoundError, ValueError) as error:
        raise _argument("pairs" if pairs else "frame_gap", error) from None
    readings = camera_to_world = None
    if ranges:
        try:
            ranges_path = Path(ranges).expanduser()
            readings = recordings.read_range_readings(
                ranges_path,
                frames.names,
                image_size,
                range_scale,
                frame_indices=lambda fields, line_numbers: files.reading_frame_indices(
                    fields,
                    line_numbers,
                    ranges_path,
                    _frame_paths(image_paths, frames.names),
                    match_frames,
                    max_time_difference,
                ),
            )
        except ArgumentError:
            raise
        except (FileNotFoundError, ValueError, OSError) as error:
            raise _argument("ranges", error) from None
        if range_metric == "ray_length":
            for frame_readings in readings.values():
                frame_readings[:, 2] = metric_scale.ray_length_to_depth(
                    frame_readings[:, :2], frame_readings[:, 2], camera_matrix
                )
    if poses:
        camera_to_world = camera_poses(
            files, poses, image_paths, frames.names, max_time_difference, match_frames
        )
    # What the model reads besides the images and flow: a given pose, the cameras, or
    # both (a given pose read against the flow).
    model_inputs = tuple(
        getattr(registry.make_model(config.model, **config.model_config), "extra_inputs", ())
    )
    if set(POSE_INPUTS) <= set(model_inputs) and camera_to_world is None:
        raise _argument(
            "poses",
            ValueError(
                "the model was trained given the relative pose: give the recording's "
                "odometry as a TUM trajectory"
            ),
        )
    if set(model_inputs) - set(POSE_INPUTS) and camera_matrix is None:
        raise _argument(
            "intrinsics",
            ValueError(
                "the model takes the camera motion from its flow's geometry, which needs the camera"
            ),
        )
    try:
        plan = recordings.plan_recording(
            frame_pairs,
            ranges=readings,
            camera_to_world=camera_to_world,
            min_baseline=min_baseline,
        )
    except ValueError as error:
        raise _argument("ranges" if ranges else "poses", error) from None

    if earlier:
        print_fn(
            f"{output_dir}: the earlier prediction's {len(earlier)} file(s) are replaced when "
            "this one is complete (--overwrite)"
        )
    predictor = DepthPredictor.from_workdir(workdir, step=step, aspect=aspect)
    try:
        with tqdm(total=len(plan.pairs), desc="predict", unit="pair") as bar:
            summary = recordings.predict_recording(
                predictor,
                frames,
                plan,
                Path(output_dir).expanduser(),
                batch_size=batch_size,
                depth_format=depth_format,
                previews=previews,
                preview_scale=preview_scale,
                camera_matrix=camera_matrix,
                ply=ply,
                overwrite=overwrite,
                progress=bar.update,
            )
    except ValueError as error:
        # A frame that cannot be read, or pairs the model refuses: the recording's fault.
        raise _argument(
            "images" if images else "video",
            ValueError(f"{error} (the run stopped there; {output_dir} is as it was)"),
        ) from None
    finally:
        frames.close()
    return summary
