"""Depth for a whole recording with a trained model: frames, pairs, range readings.

A whole recording (`python -m experiments.predict`):

    frames = ImageFolderFrames(image_paths)          # or VideoFrames("rec.mp4")
    pairs = frame_pairs(len(frames), frame_gap=1)    # or read_pairs_file(path, frames.names)
    ranges = read_range_readings("range.csv", frames.names, frames.read(0).shape[:2])
    plan = plan_recording(pairs, ranges=ranges)      # or positions=camera centres [F, 3]
    predict_recording(predictor, frames, plan, "out", depth_format="png", previews=True)

Frames are read when a batch needs them and kept only while later pairs may use them
(a bounded cache), so a long recording never sits in memory. A pair (i, j) predicts
frame i's depth; its scale comes from frame i's range readings (the rule of the
converter, `data.demon.convert`, whose records supervise frame i's depth with them;
frame j's readings are not used here, the converter needs one only because its format
refuses a view without depth) or from the distance between the two frames' camera
positions. Pairs without a measurement (no reading on frame i; a baseline not above
`min_baseline`) are skipped and counted; with neither source, depth stays in baseline
units. The output folder holds:

    depth/<frame1>__<frame2>.png   16-bit millimetres (metric depth only), or .npy float32
    preview/<frame1>__<frame2>.png image 1 beside its colourised inverse depth and a colour
                                   bar in metres (or baselines)
    ply/<frame1>__<frame2>.ply     binary PLY point cloud in the depth's units
    pairs.csv                      one row per written pair: frames, scale, source, units
    summary.json                   counts, units, skipped pairs by reason, settings

A folder holds one run, written whole or not at all (`prediction_folder`: an earlier
run's folder is refused unless `overwrite`, which replaces that run's files).
"""

from __future__ import annotations

import collections
import csv
import dataclasses
import json
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from gld import geometry
from gld.inference import depth_io, prediction_folder
from gld.inference.frames import CachedFrames
from gld.inference.inputs import check_image

DEPTH_FORMATS = ("png", "npy")


def frame_pairs(count: int, frame_gap: int = 1) -> list[tuple[int, int]]:
    """(i, i + frame_gap) for every frame i that has a partner."""
    if frame_gap < 1:
        raise ValueError(f"frame_gap must be >= 1, got {frame_gap}")
    if count <= frame_gap:
        raise ValueError(f"{count} frame(s) make no pair at frame gap {frame_gap}")
    return [(i, i + frame_gap) for i in range(count - frame_gap)]


def _frame_index(frame: str, index_of: dict[str, int], count: int) -> int | None:
    """A frame named by its name (file stem) or by its index in order."""
    if frame in index_of:
        return index_of[frame]
    if frame.isdigit() and int(frame) < count:
        return int(frame)
    return None


def read_pairs_file(path: str | Path, names: Sequence[str]) -> list[tuple[int, int]]:
    """A text file of pairs, one `frame1 frame2` per line (comma or space separated, `#`
    comments), frames by name (file stem) or index -> [(i, j)].

    Raises:
      FileNotFoundError / ValueError naming the file and line.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"pairs file {path} does not exist")
    index_of = {name: index for index, name in enumerate(names)}
    pairs = []
    for line_number, line in enumerate(path.read_text().splitlines(), 1):
        fields = line.split("#", 1)[0].replace(",", " ").split()
        if not fields:
            continue
        if len(fields) != 2:
            raise ValueError(f"{path}:{line_number}: expected 'frame1 frame2', got {line!r}")
        indices = [_frame_index(field, index_of, len(names)) for field in fields]
        for field, index in zip(fields, indices, strict=True):
            if index is None:
                raise ValueError(f"{path}:{line_number}: frame {field!r} is not a frame")
        if indices[0] == indices[1]:
            raise ValueError(f"{path}:{line_number}: a frame cannot pair with itself")
        pairs.append((indices[0], indices[1]))
    if not pairs:
        raise ValueError(f"{path}: no pairs")
    return pairs


def read_range_readings(
    path: str | Path,
    names: Sequence[str],
    image_size: tuple[int, int],
    depth_scale: float = 1.0,
    *,
    frame_indices: Callable[[list[str], list[int]], list[int]] | None = None,
) -> dict[int, np.ndarray]:
    """Range readings of the CSV format of `data.demon.convert`: `frame,u,v,depth`.

    `frame` is a frame's name (file stem) or its index in order, unless `frame_indices`
    matches them otherwise; u, v are pixels of the image ((0, 0) the top-left pixel's
    centre); depth times `depth_scale` is camera-z metres. A header line and `#`
    comments are skipped; readings whose depth is not finite or not positive (a
    sensor's "no return") are dropped, as the converter does.

    Args:
      frame_indices: maps the rows' `frame` fields and line numbers to frame indices
        (the data layer's `--match_frames`, `data.demon.recordings.reading_frame_indices`),
        raising ValueError naming the line of one it cannot match.

    Returns:
      frame index -> [N, 3] float64 (u, v, metres).

    Raises:
      FileNotFoundError / ValueError naming the file and line: a row that is not
      four fields, not numbers, of an unknown frame, or a pixel outside the image.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"range readings {path} do not exist")
    height, width = image_size
    rows: list[tuple[float, float, float]] = []
    frames: list[str] = []
    line_numbers: list[int] = []
    with path.open(newline="") as stream:
        for line_number, row in enumerate(csv.reader(stream), 1):
            if not row or not "".join(row).strip() or row[0].strip().startswith("#"):
                continue
            if len(row) != 4:
                raise ValueError(f"{path}:{line_number}: expected frame,u,v,depth, got {row}")
            try:
                u, v, depth = (float(value) for value in row[1:])
            except ValueError:
                if line_number == 1:
                    continue  # header
                raise ValueError(f"{path}:{line_number}: not numbers: {row}") from None
            if not (np.isfinite(u) and np.isfinite(v)) or not (
                -0.5 <= u <= width - 0.5 and -0.5 <= v <= height - 0.5
            ):
                raise ValueError(
                    f"{path}:{line_number}: pixel ({u}, {v}) outside the {width}x{height} image"
                )
            rows.append((u, v, depth))
            frames.append(row[0].strip())
            line_numbers.append(line_number)
    if frame_indices is None:
        index_of = {name: index for index, name in enumerate(names)}
        indices = []
        for frame, line_number in zip(frames, line_numbers, strict=True):
            index = _frame_index(frame, index_of, len(names))
            if index is None:
                raise ValueError(f"{path}:{line_number}: frame {frame!r} is not a frame")
            indices.append(index)
    else:
        # Every row, a "no return" too: `order` counts the frames the file names.
        indices = frame_indices(frames, line_numbers)
    readings: dict[int, list[tuple[float, float, float]]] = collections.defaultdict(list)
    for index, (u, v, depth) in zip(indices, rows, strict=True):
        if np.isfinite(depth) and depth > 0:
            readings[index].append((u, v, depth * depth_scale))
    return {index: np.asarray(values, np.float64) for index, values in readings.items()}


@dataclasses.dataclass
class RecordingPlan:
    """The pairs to predict, each with its scale's measurement, and those skipped."""

    pairs: list[tuple[int, int]]
    scale_source: str  # "ranges", "baseline" or "none"
    ranges: list[np.ndarray] | None = None
    baselines: list[float] | None = None
    skipped: dict[str, int] = dataclasses.field(default_factory=dict)
    # Each pair's relative pose (rotation [3, 3], translation [3] in metres), when the
    # plan was made from full camera poses.
    motions: list[tuple[np.ndarray, np.ndarray]] | None = None


def relative_motion(
    camera_to_world1: np.ndarray, camera_to_world2: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """The relative pose of a pair from two camera-to-world poses ([4, 4] or [3, 4],
    OpenCV camera axes): rotation [3, 3] and translation [3] with X2 = R X1 + t."""
    poses = []
    for pose in (camera_to_world1, camera_to_world2):
        pose = np.asarray(pose, np.float64)
        if pose.shape not in ((4, 4), (3, 4)):
            raise ValueError(f"a camera pose must be [4, 4] or [3, 4], got shape {pose.shape}")
        world_to_camera = pose[:3, :3].T
        poses.append((world_to_camera, -world_to_camera @ pose[:3, 3]))
    return geometry.relative_pose(*poses[0], *poses[1])


def plan_recording(
    pairs: Sequence[tuple[int, int]],
    *,
    ranges: dict[int, np.ndarray] | None = None,
    positions: np.ndarray | None = None,
    camera_to_world: np.ndarray | None = None,
    min_baseline: float = 0.0,
) -> RecordingPlan:
    """Attaches each pair's scale measurement and drops the pairs that have none.

    Args:
      pairs: (i, j) frame indices; depth is predicted for frame i.
      ranges: frame index -> [N, 3] readings (`read_range_readings`); a pair is scaled
        by its first frame's and skipped without (its second frame's are not used).
      positions: [F, 3] camera centres of every frame, metres; a pair's baseline is the
        distance between its frames'.
      camera_to_world: [F, 4, 4] camera poses of every frame (metres), instead of
        positions: the baseline as from their centres, and each pair's relative pose
        (`relative_motion`) for a model trained given it.
      min_baseline: pairs whose baseline is not above this are skipped.

    Raises:
      ValueError: when both sources are given, or when no pair keeps a measurement.
    """
    if sum(source is not None for source in (ranges, positions, camera_to_world)) > 1:
        raise ValueError("give one of range readings, camera positions or camera poses")
    pairs = list(pairs)
    if camera_to_world is not None:
        camera_to_world = np.asarray(camera_to_world, np.float64)
        positions = camera_to_world[:, :3, 3]
    if ranges is not None:
        kept = [pair for pair in pairs if pair[0] in ranges]
        plan = RecordingPlan(kept, "ranges", ranges=[ranges[i] for i, _ in kept])
        plan.skipped = {"no range reading on the first frame": len(pairs) - len(kept)}
    elif positions is not None:
        positions = np.asarray(positions, np.float64)
        baselines = [float(np.linalg.norm(positions[j] - positions[i])) for i, j in pairs]
        keep = [b > min_baseline and np.isfinite(b) for b in baselines]
        plan = RecordingPlan(
            [pair for pair, ok in zip(pairs, keep, strict=True) if ok],
            "baseline",
            baselines=[b for b, ok in zip(baselines, keep, strict=True) if ok],
        )
        plan.skipped = {f"baseline <= {min_baseline} m": len(pairs) - len(plan.pairs)}
        if camera_to_world is not None:
            plan.motions = [
                relative_motion(camera_to_world[i], camera_to_world[j]) for i, j in plan.pairs
            ]
    else:
        plan = RecordingPlan(pairs, "none")
    if not plan.pairs:
        reasons = ", ".join(f"{count} {reason}" for reason, count in plan.skipped.items())
        raise ValueError(f"no pair left to predict ({reasons})")
    return plan


def pair_name(names: Sequence[str], pair: tuple[int, int]) -> str:
    return f"{names[pair[0]]}__{names[pair[1]]}"


# How the previews' colours are scaled: each by its own map, or all by one.
PREVIEW_SCALES = ("pair", "recording")


def predict_recording(
    predictor,
    frames: CachedFrames,
    plan: RecordingPlan,
    out_dir: str | Path,
    *,
    batch_size: int = 8,
    depth_format: str = "png",
    previews: bool = False,
    preview_scale: str = "pair",
    camera_matrix: np.ndarray | None = None,
    ply: bool = False,
    overwrite: bool = False,
    progress: Callable[[int], None] | None = None,
) -> dict[str, Any]:
    """Predicts depth for every planned pair in batches and writes it (module docstring).

    Every batch has `batch_size` pairs (the last one padded by repeating its last pair),
    so the model is compiled once.

    Args:
      predictor: a `gld.inference.predict.DepthPredictor`.
      frames: the recording's frames (`ImageFolderFrames`, `VideoFrames`).
      plan: the pairs and their scale measurements (`plan_recording`).
      out_dir: the output folder (created); the run is moved into it when complete.
      batch_size: pairs per model call.
      depth_format: "png" (16-bit millimetres; needs metric depth) or "npy".
      previews: also write colour previews.
      preview_scale: "pair" (each preview's colours span its own map's inverse depth)
        or "recording" (one scale for all: the median of the pairs' own scales, so that
        colours compare across the recording; the previews are drawn once every depth
        map is written).
      camera_matrix: [3, 3] K of the frames (pixels), for point clouds.
      ply: write a PLY point cloud per pair (needs camera_matrix).
      overwrite: replace an earlier run's files in `out_dir` (else it is refused).
      progress: called with the number of pairs done after each batch.

    Returns:
      The summary written to summary.json.

    Raises:
      FileExistsError, ValueError: `out_dir` is refused (`prediction_folder`), before
        anything is written; ValueError naming the frames that fail, `out_dir` as it was.
    """
    if depth_format not in DEPTH_FORMATS:
        raise ValueError(f"depth format must be one of {DEPTH_FORMATS}, got {depth_format!r}")
    if depth_format == "png" and plan.scale_source == "none":
        raise ValueError(
            "16-bit PNG depth is millimetres and needs metric depth: give range readings or "
            "camera positions, or write .npy"
        )
    if ply and camera_matrix is None:
        raise ValueError("point clouds need the camera's intrinsics")
    if batch_size < 1:
        raise ValueError(f"batch_size must be >= 1, got {batch_size}")
    if preview_scale not in PREVIEW_SCALES:
        raise ValueError(f"preview scale must be one of {PREVIEW_SCALES}, got {preview_scale!r}")
    first = plan.pairs[0][0]
    check_image(frames.read(first), f"frame {frames.names[first]}")
    units = "baseline" if plan.scale_source == "none" else "metres"
    unit = "m" if units == "metres" else "x baseline"
    unstored_pixels = 0
    pair_tops: list[float] = []
    with (
        prediction_folder.staged_run(out_dir, overwrite=overwrite) as run_dir,
        (run_dir / prediction_folder.PAIRS_CSV).open("w", newline="") as stream,
    ):
        writer = csv.writer(stream)
        writer.writerow(prediction_folder.PAIRS_HEADER)
        for start in range(0, len(plan.pairs), batch_size):
            indices = list(range(start, min(start + batch_size, len(plan.pairs))))
            padded = indices + [indices[-1]] * (batch_size - len(indices))
            images1 = [frames.read(plan.pairs[k][0]) for k in padded]
            images2 = [frames.read(plan.pairs[k][1]) for k in padded]
            shapes = {image.shape for image in images1 + images2}
            if len(shapes) != 1:
                names = [pair_name(frames.names, plan.pairs[k]) for k in indices]
                raise ValueError(f"frames of different sizes {sorted(shapes)} in pairs {names}")
            options: dict[str, Any] = {}
            if plan.scale_source == "ranges":
                options["ranges"] = [plan.ranges[k] for k in padded]
            elif plan.scale_source == "baseline":
                options["baseline"] = np.array([plan.baselines[k] for k in padded])
            if getattr(predictor, "given_pose", None) == "pose":
                if plan.motions is None:
                    raise ValueError(
                        "the model was trained given the relative pose: plan the recording "
                        "with camera poses (camera_to_world=, --poses) to give it the odometry"
                    )
                options["rotation"] = np.stack([plan.motions[k][0] for k in padded])
                options["translation"] = np.stack([plan.motions[k][1] for k in padded])
            if getattr(predictor, "needs_camera", False):
                if camera_matrix is None:
                    raise ValueError(
                        "the model takes the camera motion from its flow: give the camera's "
                        "intrinsics"
                    )
                options["intrinsics"] = camera_matrix
            try:
                outputs = predictor.predict(np.stack(images1), np.stack(images2), **options)
            except ValueError as error:
                names = [pair_name(frames.names, plan.pairs[k]) for k in indices]
                raise ValueError(f"pairs {names[0]} .. {names[-1]}: {error}") from None
            for position, k in enumerate(indices):
                name = pair_name(frames.names, plan.pairs[k])
                depth = outputs["depth"][position]
                depth_path = run_dir / "depth" / f"{name}.{depth_format}"
                if depth_format == "png":
                    unstored_pixels += depth_io.write_depth_png(depth_path, depth)
                else:
                    depth_io.write_depth_npy(depth_path, depth)
                colour_image = _display_image(images1[position])
                if previews and preview_scale == "pair":
                    depth_io.write_preview(
                        run_dir / "preview" / f"{name}.png", colour_image, depth, unit=unit
                    )
                pair_tops.append(depth_io.inverse_depth_top(depth))
                if ply:
                    points, colours = depth_io.point_cloud(depth, camera_matrix, colour_image)
                    depth_io.write_ply(run_dir / "ply" / f"{name}.ply", points, colours)
                first, second = plan.pairs[k]
                writer.writerow(
                    [
                        name,
                        frames.names[first],
                        frames.names[second],
                        f"{float(outputs['scale'][position]):.6g}",
                        plan.scale_source,
                        units,
                        depth_path.relative_to(run_dir).as_posix(),
                    ]
                )
            stream.flush()
            if progress is not None:
                progress(len(indices))
        if previews and preview_scale == "recording":
            top = float(np.median(pair_tops))
            for first_frame, second_frame in plan.pairs:
                name = pair_name(frames.names, (first_frame, second_frame))
                depth = _written_depth(run_dir / "depth" / f"{name}.{depth_format}")
                image = _display_image(frames.read(first_frame))
                depth_io.write_preview(
                    run_dir / "preview" / f"{name}.png", image, depth, top=top, unit=unit
                )
        summary = {
            "pairs_written": len(plan.pairs),
            "pairs_skipped": plan.skipped,
            "scale_source": plan.scale_source,
            "units": units,
            "depth_format": depth_format,
            "png_depth_scale": depth_io.PNG_DEPTH_SCALE if depth_format == "png" else None,
            "png_unstored_pixels": unstored_pixels if depth_format == "png" else None,
            "previews": previews,
            "preview_scale": preview_scale if previews else None,
            "ply": ply,
            "camera_matrix": None if camera_matrix is None else np.asarray(camera_matrix).tolist(),
            "model_resolution": [predictor.height, predictor.width],
            "aspect": predictor.aspect,
        }
        (run_dir / prediction_folder.SUMMARY).write_text(json.dumps(summary, indent=2) + "\n")
    return summary


def _written_depth(path: Path) -> np.ndarray:
    """A depth map this module wrote, as [H, W] float32 depth, NaN where there is none."""
    if path.suffix == ".npy":
        return np.load(path)
    values = cv2.imread(str(path), cv2.IMREAD_UNCHANGED).astype(np.float32)
    return np.where(values > 0, values * depth_io.PNG_DEPTH_SCALE, np.nan).astype(np.float32)


def _display_image(image: np.ndarray) -> np.ndarray:
    """A frame as [H, W, 3] uint8 RGB for previews and point colours."""
    image = np.asarray(image)
    if image.dtype != np.uint8:
        image = np.clip(image.astype(np.float64) * 255.0 + 0.5, 0, 255).astype(np.uint8)
    if image.ndim == 2:
        image = image[..., None]
    if image.shape[-1] == 1:
        image = np.repeat(image, 3, axis=-1)
    return image[..., :3]
