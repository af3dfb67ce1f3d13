"""Which pose, depth image and range reading belongs to which image of a recording: the
converter's and the predictor's `--match_frames` (`MATCH_FRAMES`).

`auto` takes the same name, else the nearest time stamp when both sides have one, else
the order (range readings: the image's name, else its index); `time` the nearest time
stamp, within `max_time_difference` seconds; `order` the i-th pose, depth image or
frame of the range readings for the i-th image (as many of each). A name is a time
stamp only when it is a plain decimal number of seconds (`time_stamp`): `07_1.png`,
`1e5.png` and `nan.png` are not. A time match that fails on images named like frame
numbers says that `--match_frames=order` matches by order.
"""

from __future__ import annotations

import re
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from gld.arguments import ArgumentError

DEPTH_SUFFIXES = (".png", ".npy", ".tif", ".tiff")
MATCH_FRAMES = ("auto", "time", "order")

_TIME_STAMP = re.compile(r"[0-9]+(?:\.[0-9]+)?", re.ASCII)

# A name over this many seconds from every time stamp was never one (frame numbers beside
# a trajectory's Unix times), whatever its form.
_FOREIGN_TIME_GAP = 3600.0


def time_stamp(name: str) -> float | None:
    """A name (a file's stem, a CSV's frame) as a time stamp in seconds, or None when it is
    not a plain decimal number."""
    return float(name) if _TIME_STAMP.fullmatch(name) else None


def _times(paths: Sequence[Path]) -> np.ndarray | None:
    """File names as time stamps [N] (TUM names files by time), or None if any is not one."""
    times = [time_stamp(path.stem) for path in paths]
    return None if None in times else np.array(times, np.float64)


def check_match_frames(match_frames: str) -> None:
    """Raises ArgumentError naming `--match_frames` when it is not one of `MATCH_FRAMES`."""
    if match_frames not in MATCH_FRAMES:
        raise ArgumentError(
            f"--match_frames={match_frames}: must be one of {', '.join(MATCH_FRAMES)}"
        )


def _image_times(image_paths: Sequence[Path]) -> np.ndarray:
    """The images' time stamps [N] for `--match_frames=time`; ArgumentError naming one
    that is not named by a time stamp."""
    for path in image_paths:
        if time_stamp(path.stem) is None:
            raise ArgumentError(
                f"--match_frames=time: {path} is not named by a time stamp (a plain decimal "
                "number of seconds, e.g. 1305031102.175304.png); --match_frames=order matches "
                "by order"
            )
    return _times(image_paths)


def _looks_numbered(image_paths: Sequence[Path], gap: float, max_time_difference: float) -> bool:
    """Whether images whose time match failed by `gap` seconds look numbered by frame, not
    named by time stamp: whole numbers over a second (and 100 x max_time_difference)
    from a stamp, or any names over an hour from one."""
    whole = all(path.stem.isascii() and path.stem.isdigit() for path in image_paths)
    return (whole and gap > max(1.0, 100 * max_time_difference)) or gap > _FOREIGN_TIME_GAP


def _nearest_in_time(
    query_times: np.ndarray,
    reference_times: np.ndarray,
    max_time_difference: float,
    query_names: Sequence[str | Path],
    *,
    image_paths: Sequence[Path],
    match_frames: str,
    reference: str,
) -> np.ndarray:
    """Index into `reference_times` [M] of the nearest time to each query time [N].

    Args:
      query_names: [N] what each query time is, for errors.
      image_paths: the images, whose names are judged when the match fails.
      match_frames: the `--match_frames` value, for errors.
      reference: what a reference time stamps ("pose", "image", ...), for errors.

    Raises:
      ArgumentError: a query over `max_time_difference` from every reference. It names
        `--match_frames` and says that `order` matches by order when the images look
        numbered by frame (`_looks_numbered`), else `--max_time_difference`.
    """
    order = np.argsort(reference_times)
    sorted_times = reference_times[order]
    right = np.clip(np.searchsorted(sorted_times, query_times), 0, len(sorted_times) - 1)
    left = np.clip(right - 1, 0, len(sorted_times) - 1)
    use_left = np.abs(query_times - sorted_times[left]) <= np.abs(sorted_times[right] - query_times)
    nearest = np.where(use_left, left, right)
    gaps = np.abs(sorted_times[nearest] - query_times)
    if np.any(gaps > max_time_difference):
        worst = int(np.argmax(gaps))
        where = (
            f"{query_names[worst]} is {gaps[worst]:.3f} s from the nearest {reference}'s time stamp"
        )
        if _looks_numbered(image_paths, float(gaps[worst]), max_time_difference):
            other = "frame of the readings" if reference == "image" else reference
            raise ArgumentError(
                f"--match_frames={match_frames}: {where}: the images' names (e.g. "
                f"{image_paths[0].name}) look like frame numbers, not time stamps; "
                f"--match_frames=order matches the i-th image to the i-th {other}"
            )
        raise ArgumentError(f"--max_time_difference={max_time_difference}: {where}")
    return order[nearest]


def _by_order(count: int, num_images: int, what: str, match_frames: str, hint: str) -> np.ndarray:
    """0..N-1, the i-th of `what` for the i-th image, when there are as many as images."""
    if count != num_images:
        message = f"{num_images} images but {count} {what}"
        if match_frames == "order":
            raise ArgumentError(f"--match_frames=order: {message}; order needs one per image")
        raise ValueError(f"{message}; {hint}")
    return np.arange(num_images)


def associate_poses(
    image_paths: Sequence[Path],
    timestamps: np.ndarray | None,
    num_poses: int,
    max_time_difference: float,
    match_frames: str = "auto",
) -> np.ndarray:
    """Pose index of every image [N], as `match_frames` says (module docstring).

    Args:
      image_paths: [N] the images, in name order.
      timestamps: [num_poses] the poses' time stamps, None when they have none.
      num_poses: how many poses.
      max_time_difference: seconds an image may be from its pose's time stamp.
      match_frames: `auto` (by time when the images are named by time stamp and the
        poses have stamps, else by order), `time` or `order`.

    Raises:
      ArgumentError: naming `--match_frames` when `time` finds no time stamp (or names
        that look like frame numbers) or `order` has not one pose per image; naming
        `--max_time_difference` when an image has no pose near enough in time.
      ValueError: `auto` by order, with not one pose per image.
    """
    check_match_frames(match_frames)
    if match_frames == "time":
        if timestamps is None:
            raise ArgumentError(
                "--match_frames=time: the poses have no time stamps (a TUM trajectory has); "
                "--match_frames=order matches the i-th image to the i-th pose"
            )
        image_times = _image_times(image_paths)
    else:
        image_times = _times(image_paths) if match_frames == "auto" else None
    if timestamps is not None and image_times is not None:
        return _nearest_in_time(
            image_times,
            timestamps,
            max_time_difference,
            image_paths,
            image_paths=image_paths,
            match_frames=match_frames,
            reference="pose",
        )
    return _by_order(
        num_poses,
        len(image_paths),
        "poses",
        match_frames,
        "name images by time stamp or give one pose per image",
    )


def associate_depth_files(
    folder: Path,
    image_paths: Sequence[Path],
    max_time_difference: float,
    match_frames: str = "auto",
) -> list[Path]:
    """The depth file of every image, as `match_frames` says: `auto` the same name, else
    the nearest time stamp, else the order; `time` the nearest time stamp; `order` the
    i-th in name order.

    Raises:
      ArgumentError: as `associate_poses`, naming a depth file without a time stamp.
      ValueError: `auto` by order, with not one depth file per image.
    """
    check_match_frames(match_frames)
    depth_paths = sorted(p for p in folder.iterdir() if p.suffix.lower() in DEPTH_SUFFIXES)
    if not depth_paths:
        raise FileNotFoundError(f"no depth images ({', '.join(DEPTH_SUFFIXES)}) in {folder}")
    by_stem = {path.stem: path for path in depth_paths}
    if match_frames == "auto" and all(path.stem in by_stem for path in image_paths):
        return [by_stem[path.stem] for path in image_paths]
    if match_frames == "time":
        image_times = _image_times(image_paths)
        for path in depth_paths:
            if time_stamp(path.stem) is None:
                raise ArgumentError(
                    f"--match_frames=time: depth image {path} is not named by a time stamp"
                )
        depth_times = _times(depth_paths)
    elif match_frames == "auto":
        image_times, depth_times = _times(image_paths), _times(depth_paths)
    else:
        image_times = depth_times = None
    if image_times is not None and depth_times is not None:
        nearest = _nearest_in_time(
            image_times,
            depth_times,
            max_time_difference,
            image_paths,
            image_paths=image_paths,
            match_frames=match_frames,
            reference="depth image",
        )
        return [depth_paths[index] for index in nearest]
    _by_order(
        len(depth_paths),
        len(image_paths),
        f"depth images in {folder}",
        match_frames,
        "name them like the images, by time stamp, or give one per image",
    )
    return depth_paths


def reading_frame_indices(
    frames: Sequence[str],
    line_numbers: Sequence[int],
    csv_path: Path,
    image_paths: Sequence[Path],
    match_frames: str = "auto",
    max_time_difference: float = 0.02,
) -> list[int]:
    """The image of every row of a range readings CSV, from its `frame` field.

    `auto`: the image's name (file stem), else its index in name order. `time`: the
    image nearest in time (`frame` and the images named by time stamp), within
    `max_time_difference`. `order`: the frames, in the order they first appear, are the
    images in name order (as many frames as images; `frame` only groups the rows).

    Args:
      frames: [R] the rows' `frame` fields.
      line_numbers: [R] the rows' lines in `csv_path` (from 1), for errors.
      csv_path: the CSV, for errors.
      image_paths: the images, in name order.

    Raises:
      ValueError: naming the file and line of a frame that is no image (`auto`).
      ArgumentError: naming `--match_frames` (`time`: a frame or image that is not a
        time stamp; `order`: not as many frames as images) or `--max_time_difference`.
    """
    check_match_frames(match_frames)
    if match_frames == "order":
        first_seen = list(dict.fromkeys(frames))
        if len(first_seen) != len(image_paths):
            raise ArgumentError(
                f"--match_frames=order: {len(image_paths)} images but {csv_path} has "
                f"readings of {len(first_seen)} frames; order needs the readings of every image"
            )
        index_of = {frame: index for index, frame in enumerate(first_seen)}
        return [index_of[frame] for frame in frames]
    if match_frames == "time":
        image_times = _image_times(image_paths)
        reading_times = []
        for frame, line_number in zip(frames, line_numbers, strict=True):
            if (reading_time := time_stamp(frame)) is None:
                raise ArgumentError(
                    f"--match_frames=time: {csv_path}:{line_number}: frame {frame!r} is not a "
                    "time stamp"
                )
            reading_times.append(reading_time)
        where = [
            f"{csv_path}:{line_number}: frame {frame}"
            for frame, line_number in zip(frames, line_numbers, strict=True)
        ]
        nearest = _nearest_in_time(
            np.array(reading_times, np.float64),
            image_times,
            max_time_difference,
            where,
            image_paths=image_paths,
            match_frames="time",
            reference="image",
        )
        return [int(index) for index in nearest]
    index_of = {path.stem: index for index, path in enumerate(image_paths)}
    indices = []
    for frame, line_number in zip(frames, line_numbers, strict=True):
        index = index_of.get(frame)
        if index is None and frame.isascii() and frame.isdigit() and int(frame) < len(image_paths):
            index = int(frame)
        if index is None:
            raise ValueError(f"{csv_path}:{line_number}: frame {frame!r} is not an image")
        indices.append(index)
    return indices
