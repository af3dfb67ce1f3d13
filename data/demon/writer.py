"""Writes DeMoN-format HDF5 files: one view, and a whole recording for `demon/custom`.

`write_view` stores a view as DeMoN does (WebP image, LZ4-block float16 depth,
17-value camera from `demon_camera`); `write_recording` reads a recording
(`recordings`), pairs its frames, splits them into train and test, and writes
`custom_<split>.h5` (`output_path`), the files the `demon/custom` config reads: all
of them or none, never over an existing file unless asked to.

Depth readings and pairs: a pair (i, j) is frame i's depth. Training supervises it with
frame i's readings (the records' `depth1`; the predictor, `gld.inference.recordings`,
scales a pair by them), so a pair needs a reading on frame i. It needs one on frame j
too, for the format: the `demon/custom` reader refuses a view without depth as damage
(`reader.read_view`, `invalid_depth`); frame j's depth (`depth2`) serves only the
ground-truth flow's occlusion test. A pair without is left out and counted by the frame
that lacks a reading (`NO_READING_REASONS`).
"""

from __future__ import annotations

import collections
import os
import re
import tempfile
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import cv2
import h5py
import lz4.block
import numpy as np

from data.demon import recordings

# Why a pair is left out: its first frame (whose depth it is) or its second frame (which
# the reader refuses without depth) has no depth reading.
NO_READING_REASONS = ("no_reading_on_first_frame", "no_reading_on_second_frame")


def demon_camera(camera_matrix: np.ndarray, rotation: np.ndarray, translation: np.ndarray):
    """Pixel-index K, world-to-camera R, t -> DeMoN's 17 camera values.

    DeMoN's K has its origin at the top-left corner and R is stored column-major.
    """
    return np.concatenate(
        [
            [camera_matrix[0, 0], camera_matrix[1, 1], 0.0],
            [camera_matrix[0, 2] + 0.5, camera_matrix[1, 2] + 0.5],
            rotation.T.reshape(-1),  # column-major
            translation,
        ]
    ).astype(np.float64)


def write_view(
    view_group: h5py.Group,
    image: np.ndarray,
    depth: np.ndarray,
    camera: np.ndarray,
    depth_metric: str,
    webp_quality: int,
) -> None:
    """Writes one DeMoN view: WebP image, LZ4-block float16 depth with extents, camera."""
    ok, encoded = cv2.imencode(
        ".webp", cv2.cvtColor(image, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_WEBP_QUALITY, webp_quality]
    )
    if not ok:
        raise ValueError(f"OpenCV could not encode {view_group.name}/image as WebP")
    dataset = view_group.create_dataset("image", data=np.frombuffer(encoded.tobytes(), np.int8))
    dataset.attrs["format"] = np.bytes_("webp")
    depth16 = np.ascontiguousarray(np.minimum(depth, np.finfo(np.float16).max), np.float16)
    compressed = lz4.block.compress(depth16.tobytes(), store_size=False)
    dataset = view_group.create_dataset("depth", data=np.frombuffer(compressed, np.int8))
    dataset.attrs["format"] = np.bytes_("lz4half")
    dataset.attrs["extents"] = np.asarray(depth.shape, np.int32)
    dataset.attrs["depth_metric"] = np.bytes_(depth_metric)
    dataset = view_group.create_dataset("camera", data=camera)
    dataset.attrs["format"] = np.bytes_("pinhole")


# A recording name: letters, digits, '_', '-', '.', not starting with '.', so that the
# file stays in the output folder and is not hidden.
_RECORDING_NAME = re.compile(r"[A-Za-z0-9_-][A-Za-z0-9_.-]*")


def _source(image_paths: Sequence[Path]) -> str:
    """The recording a file is written from: its frames' folder, resolved."""
    return str(Path(image_paths[0]).parent.resolve())


def _source_of(path: Path) -> str | None:
    """The recording a written file came from (None when unreadable or not recorded)."""
    try:
        with h5py.File(path, "r") as h5_file:
            source = h5_file[".config"].attrs["source"]
    except (OSError, KeyError):
        return None
    return source.decode() if isinstance(source, bytes) else str(source)


def output_path(output_dir: str | Path, split: str, recording: str | None = None) -> Path:
    """`custom_<split>.h5` or `custom_<split>_<recording>.h5`, the names `demon/custom` reads.

    Raises:
      ValueError: naming `recording` when it is not a plain name (a path separator,
        '..' or a leading '.' would put the file elsewhere or hide it).
    """
    if split not in ("train", "test"):
        raise ValueError(f"split must be 'train' or 'test', got {split!r}")
    if recording and (not _RECORDING_NAME.fullmatch(recording) or ".." in recording):
        raise ValueError(
            f"--recording={recording!r}: a recording name may hold letters, digits, '_', '-' "
            "and '.' (not first, no '..'); it names custom_<split>_<recording>.h5 inside "
            "--output_dir"
        )
    suffix = f"_{recording}" if recording else ""
    return Path(output_dir).expanduser() / f"custom_{split}{suffix}.h5"


def _write_pairs(
    path: Path,
    pair_list: list[tuple[int, int]],
    image_paths: list[Path],
    first_image: np.ndarray,
    frame_depth: Callable[[int], np.ndarray],
    cameras: Sequence[np.ndarray],
    depth_metric: str,
    webp_quality: int,
    dropped: collections.Counter,
) -> int:
    """Writes one scene group per pair into a new HDF5 file; returns how many.

    A pair without a depth reading on either frame is left out and counted in `dropped`
    by the first such frame (`NO_READING_REASONS`; module docstring).
    `first_image` [H, W, 3] is frame 0's, the size every image must have.
    """
    written = 0
    with h5py.File(path, "w") as h5_file:
        h5_file.create_group(".config").attrs["source"] = np.bytes_(_source(image_paths))
        for i, j in pair_list:
            depths = {index: frame_depth(index) for index in (i, j)}
            unread = [not np.any(depths[frame] > 0) for frame in (i, j)]
            if any(unread):
                dropped[NO_READING_REASONS[unread.index(True)]] += 1
                continue
            group_name = f"{image_paths[i].stem}__{image_paths[j].stem}"
            t0 = h5_file.create_group(f"{group_name}/frames/t0")
            t0.attrs["viewpoint_pairs"] = np.array([0, 1], np.int32)
            t0.attrs["frames"] = np.array([image_paths[i].name, image_paths[j].name], "S")
            for view_index, frame in enumerate((i, j)):
                image = first_image if frame == 0 else recordings.read_image(image_paths[frame])
                if image.shape != first_image.shape:
                    raise ValueError(
                        f"{image_paths[frame]} is {image.shape}, the first image "
                        f"{first_image.shape}; all images need one size and one camera"
                    )
                write_view(
                    t0.create_group(f"v{view_index}"),
                    image,
                    depths[frame],
                    cameras[frame],
                    depth_metric,
                    webp_quality,
                )
            written += 1
    return written


def write_recording(
    images: str | Path,
    poses: str | Path,
    intrinsics: str,
    output_dir: str | Path,
    *,
    depth: str | Path,
    pose_format: str = "tum",
    pose_direction: str = "camera_to_world",
    depth_scale: float = 1.0,
    depth_metric: str = "camera_z",
    frame_gap: int = 1,
    min_baseline: float | None = None,
    max_baseline: float | None = None,
    max_frame_gap: int = 30,
    test_fraction: float = 0.0,
    split: str = "train",
    recording: str | None = None,
    webp_quality: int = 101,
    max_time_difference: float = 0.02,
    match_frames: str = "auto",
    overwrite: bool = False,
) -> dict[str, Any]:
    """Writes a recording as DeMoN-format file(s), pairing its frames and splitting them.

    The arguments are `python -m data.demon.convert`'s flags; its docstring describes
    the inputs, the pairing and the output. All or nothing: every file is written to a
    temporary file in `output_dir` and moved into place only when every split asked
    for (train and test with `test_fraction` > 0, else `split`) has at least one pair.

    Re-converting a recording replaces all of its files: with `overwrite`, the same
    recording's file of the split not written now is removed (its pairs would overlap);
    without, it is refused. A file of another recording under the other split's name stays.

    Returns:
      {"files": {split: path}, "pairs": {split: count}, "dropped": {reason: count},
       "removed": [the same recording's earlier file of the other split]}.

    Raises:
      FileExistsError: an output file, or the same recording's file of the other split,
        exists and `overwrite` is False (before any frame is read).
      ArgumentError: poses, depth images or range readings cannot be matched to the
        images as `match_frames` says (naming `--match_frames` or
        `--max_time_difference`); nothing is written then.
      ValueError: an input is malformed (naming the file and line or the argument), or
        a split would get no pair; nothing is written then.
    """
    if pose_format not in recordings.POSE_FORMATS:
        raise ValueError(
            f"pose_format must be one of {recordings.POSE_FORMATS}, got {pose_format!r}"
        )
    if depth_metric not in recordings.DEPTH_METRICS:
        raise ValueError(
            f"depth_metric must be one of {recordings.DEPTH_METRICS}, got {depth_metric!r}"
        )
    if split not in ("train", "test"):
        raise ValueError(f"split must be 'train' or 'test', got {split!r}")
    if not 0.0 <= test_fraction < 1.0:
        raise ValueError(f"test_fraction must be in [0, 1), got {test_fraction}")
    if not (np.isfinite(depth_scale) and depth_scale > 0):
        raise ValueError(f"depth_scale must be a finite number > 0, got {depth_scale}")
    if not max_time_difference >= 0:
        raise ValueError(f"max_time_difference must be >= 0, got {max_time_difference}")
    recordings.check_match_frames(match_frames)
    output_dir = Path(output_dir).expanduser()
    splits = ("train", "test") if test_fraction > 0 else (split,)
    outputs = {name: output_path(output_dir, name, recording) for name in splits}
    existing = [str(path) for path in outputs.values() if path.exists()]
    if existing and not overwrite:
        raise FileExistsError(
            f"{', '.join(existing)} already exist(s); pass --overwrite (overwrite=True) to "
            "replace, or choose another --output_dir or --recording"
        )

    image_paths = recordings.list_images(images)
    # The same recording's file of the split not written now (an earlier conversion with
    # --test_fraction, or with the other --split) would put its frames in both splits.
    same_recording = [
        path
        for name in ("train", "test")
        if name not in outputs
        and (path := output_path(output_dir, name, recording)).exists()
        and _source_of(path) == _source(image_paths)
    ]
    if same_recording and not overwrite:
        raise FileExistsError(
            f"{', '.join(map(str, same_recording))} holds pairs of the same recording "
            f"({_source(image_paths)}): writing its {split} split beside it would put the "
            "same frames in both splits; pass --overwrite to replace it, or --test_fraction "
            "to split the recording"
        )
    if pose_format == "tum":
        timestamps, camera_to_world = recordings.read_tum_trajectory(poses)
        rotations, translations = recordings.world_to_camera(camera_to_world, "camera_to_world")
    else:
        timestamps = None
        rotations, translations = recordings.world_to_camera(
            recordings.read_pose_matrices(poses), pose_direction
        )
    pose_index = recordings.associate_poses(
        image_paths, timestamps, len(rotations), max_time_difference, match_frames
    )
    rotations, translations = rotations[pose_index], translations[pose_index]
    first_image = recordings.read_image(image_paths[0])
    camera_matrix = recordings.read_intrinsics(str(intrinsics), first_image.shape[:2])
    centres = -np.einsum("nji,nj->ni", rotations, translations)  # -R^T t
    cameras = [
        demon_camera(camera_matrix, rotation, translation)
        for rotation, translation in zip(rotations, translations, strict=True)
    ]

    depth_path = Path(depth).expanduser()
    if depth_path.is_dir():
        depth_maps = None
        depth_files = recordings.associate_depth_files(
            depth_path, image_paths, max_time_difference, match_frames
        )
    elif depth_path.suffix.lower() == ".csv":
        depth_maps = recordings.read_sparse_depth(
            depth_path,
            image_paths,
            first_image.shape[:2],
            depth_scale,
            match_frames,
            max_time_difference,
        )
    else:
        raise FileNotFoundError(f"depth {depth_path} is neither a folder nor a .csv file")

    def frame_depth(index: int) -> np.ndarray:
        if depth_maps is not None:
            return depth_maps[index]
        return recordings.read_dense_depth(depth_files[index], depth_scale)

    candidate_pairs = recordings.select_pairs(
        centres, frame_gap, min_baseline, max_baseline, max_frame_gap
    )
    dropped: collections.Counter = collections.Counter()
    first_test_frame = int(np.ceil(len(image_paths) * (1.0 - test_fraction)))
    split_pairs: dict[str, list[tuple[int, int]]] = {name: [] for name in splits}
    for pair in candidate_pairs:
        if test_fraction == 0.0:
            split_pairs[split].append(pair)
        elif pair[1] < first_test_frame:
            split_pairs["train"].append(pair)
        elif pair[0] >= first_test_frame:
            split_pairs["test"].append(pair)
        else:
            dropped["crosses_split_boundary"] += 1
    empty = [name for name, pair_list in split_pairs.items() if not pair_list]
    if empty:
        raise ValueError(
            f"{images}: {len(image_paths)} frames give no {' or '.join(empty)} pairs "
            f"({len(candidate_pairs)} candidate pairs, frame_gap={frame_gap}, "
            f"min_baseline={min_baseline}, max_baseline={max_baseline}, "
            f"test_fraction={test_fraction}, dropped: {dict(dropped)}); nothing written"
        )

    created_output_dir = not output_dir.exists()
    output_dir.mkdir(parents=True, exist_ok=True)
    temporary: dict[str, Path] = {}
    counts: dict[str, int] = {}
    try:
        for split_name, pair_list in split_pairs.items():
            # A hidden name the builder's globs do not match, in the same folder so that
            # the final os.replace is a rename.
            descriptor, name = tempfile.mkstemp(
                prefix=f".{outputs[split_name].name}.", suffix=".tmp", dir=output_dir
            )
            os.close(descriptor)
            temporary[split_name] = Path(name)
            counts[split_name] = _write_pairs(
                temporary[split_name],
                pair_list,
                image_paths,
                first_image,
                frame_depth,
                cameras,
                depth_metric,
                webp_quality,
                dropped,
            )
        empty = [name for name, count in counts.items() if count == 0]
        if empty:
            raise ValueError(
                f"{images}: no {' or '.join(empty)} pair has a depth reading on both its "
                "frames (the first frame's is the pair's depth; the demon/custom reader refuses "
                f"a view without depth) (dropped: {dict(dropped)}); nothing written"
            )
        for split_name, path in temporary.items():
            os.replace(path, outputs[split_name])
        # With --overwrite the recording's earlier other split goes: it overlaps this one.
        for path in same_recording:
            path.unlink(missing_ok=True)
    except BaseException:
        for path in temporary.values():
            path.unlink(missing_ok=True)
        if created_output_dir and not any(output_dir.iterdir()):
            output_dir.rmdir()
        raise
    return {
        "files": dict(outputs),
        "pairs": counts,
        "dropped": dict(dropped),
        "removed": [str(path) for path in same_recording],
    }
