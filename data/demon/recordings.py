"""A robot's recording, read frame by frame: images, trajectory, intrinsics, depth, pairs.

Readers of what `python -m data.demon.convert` takes (its docstring describes the
formats): TUM trajectories and 4x4 pose matrices turned into DeMoN's world-to-camera
poses, intrinsics in OpenCV pixels, images, dense depth images and sparse range
readings. Poses, depth images and range readings are matched to the images as
`--match_frames` says (`MATCH_FRAMES`), and `select_pairs` chooses the frame pairs to
write.

Matching frames, the converter's and the predictor's `--match_frames` (the predictor
reads a recording with these functions, `gld.inference.recording_run.RecordingFiles`):
`auto` takes the same name, else the nearest time stamp when both sides have one, else
the order (range readings: the image's name, else its index); `time` the nearest time
stamp, within `max_time_difference` seconds; `order` the i-th pose, depth image or
frame of the range readings for the i-th image (as many of each). A name is a time
stamp only when it is a plain decimal number of seconds (`time_stamp`).
"""

from __future__ import annotations

import csv
import re
from collections.abc import Sequence
from pathlib import Path

import cv2
import numpy as np

from gld.arguments import ArgumentError

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".webp", ".ppm")
DEPTH_SUFFIXES = (".png", ".npy", ".tif", ".tiff")
POSE_FORMATS = ("tum", "matrix")
POSE_DIRECTIONS = ("camera_to_world", "world_to_camera")
DEPTH_METRICS = ("camera_z", "ray_length")
MATCH_FRAMES = ("auto", "time", "order")


def quaternion_to_rotation(quaternion: np.ndarray) -> np.ndarray:
    """Unit quaternions [..., 4] as (qx, qy, qz, qw) -> rotation matrices [..., 3, 3]."""
    norm = np.linalg.norm(quaternion, axis=-1, keepdims=True)
    if np.any(norm < 1e-9):
        raise ValueError("zero quaternion in the trajectory")
    x, y, z, w = np.moveaxis(quaternion / norm, -1, 0)
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], -1),
            np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], -1),
            np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], -1),
        ],
        -2,
    )


def _numeric_rows(path: Path, widths: Sequence[int]) -> tuple[np.ndarray, list[int]]:
    """Whitespace/comma separated numbers, one record per line, `#` comments skipped.

    Returns:
      The records [N, width] and the line number (from 1) of each.

    Raises:
      ValueError: naming the file and line of a record that is not all finite numbers,
        has a width not in `widths`, or differs in width from the first.
    """
    rows, line_numbers = [], []
    for line_number, line in enumerate(path.read_text().splitlines(), 1):
        line = line.split("#", 1)[0].replace(",", " ").strip()
        if not line:
            continue
        try:
            values = [float(value) for value in line.split()]
        except ValueError:
            raise ValueError(f"{path}:{line_number}: not numbers: {line!r}") from None
        if len(values) not in widths:
            raise ValueError(
                f"{path}:{line_number}: expected {' or '.join(map(str, widths))} numbers, "
                f"got {len(values)}"
            )
        if not np.all(np.isfinite(values)):
            raise ValueError(f"{path}:{line_number}: NaN or infinite value in {line!r}")
        if rows and len(values) != len(rows[0]):
            raise ValueError(
                f"{path}:{line_number}: {len(values)} numbers, but {len(rows[0])} on line "
                f"{line_numbers[0]}"
            )
        rows.append(values)
        line_numbers.append(line_number)
    if not rows:
        raise ValueError(f"{path}: no records")
    return np.asarray(rows, np.float64), line_numbers


def read_tum_trajectory(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """TUM `timestamp tx ty tz qx qy qz qw` lines -> timestamps [N], camera-to-world [N, 4, 4].

    Raises:
      ValueError: naming the file and line of a value that is not a finite number or
        of a zero quaternion.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"trajectory {path} does not exist")
    rows, line_numbers = _numeric_rows(path, (8,))
    norms = np.linalg.norm(rows[:, 4:8], axis=-1)
    if np.any(norms < 1e-9):
        line_number = line_numbers[int(np.argmax(norms < 1e-9))]
        raise ValueError(f"{path}:{line_number}: zero quaternion (qx qy qz qw all 0)")
    camera_to_world = np.tile(np.eye(4), (len(rows), 1, 1))
    camera_to_world[:, :3, :3] = quaternion_to_rotation(rows[:, 4:8])
    camera_to_world[:, :3, 3] = rows[:, 1:4]
    return rows[:, 0], camera_to_world


# A pose's rotation block may deviate this much from orthonormal (the builder's
# tolerance for a camera, `reader.parse_camera`).
ROTATION_TOLERANCE = 1e-3


def check_poses(matrices: np.ndarray, where: Sequence[str]) -> None:
    """Checks 4x4 rigid poses [N, 4, 4]: finite, a rotation block and last row [0 0 0 1].

    Args:
      matrices: [N, 4, 4] poses.
      where: [N] names of the poses' origins in errors ("file:line" or "file[index]").

    Raises:
      ValueError: naming the first pose that is not a rigid transform.
    """
    for index, matrix in enumerate(matrices):
        if not np.all(np.isfinite(matrix)):
            raise ValueError(f"{where[index]}: pose contains NaN or inf")
        if np.abs(matrix[3] - [0.0, 0.0, 0.0, 1.0]).max() > 1e-6:
            raise ValueError(f"{where[index]}: last row {matrix[3].tolist()} is not [0 0 0 1]")
        rotation = matrix[:3, :3]
        error = np.abs(rotation @ rotation.T - np.eye(3)).max()
        if error > ROTATION_TOLERANCE or np.linalg.det(rotation) < 0:
            raise ValueError(
                f"{where[index]}: the upper-left 3x3 block is not a rotation "
                f"(|R R^T - I| = {error:.2g}, det = {np.linalg.det(rotation):.3g})"
            )


def read_pose_matrices(path: str | Path) -> np.ndarray:
    """`.npy` [N, 4, 4] or text lines of 16 (or timestamp + 16) numbers -> [N, 4, 4].

    Raises:
      ValueError: naming the file and line (or index) of a pose that is not a finite
        rigid transform (`check_poses`).
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"pose file {path} does not exist")
    if path.suffix == ".npy":
        matrices = np.load(path).astype(np.float64)
        where = [f"{path}[{index}]" for index in range(len(matrices))]
    else:
        rows, line_numbers = _numeric_rows(path, (16, 17))
        matrices = rows[:, -16:].reshape(-1, 4, 4)
        where = [f"{path}:{line_number}" for line_number in line_numbers]
    if matrices.ndim != 3 or matrices.shape[1:] != (4, 4):
        raise ValueError(f"{path}: expected [N, 4, 4] poses, got shape {matrices.shape}")
    check_poses(matrices, where)
    return matrices


def world_to_camera(pose: np.ndarray, direction: str) -> tuple[np.ndarray, np.ndarray]:
    """A 4x4 pose [N, 4, 4] -> DeMoN's world-to-camera (R [N, 3, 3], t [N, 3])."""
    if direction not in POSE_DIRECTIONS:
        raise ValueError(f"pose direction must be one of {POSE_DIRECTIONS}, got {direction!r}")
    rotation, translation = pose[:, :3, :3], pose[:, :3, 3]
    if direction == "world_to_camera":
        return rotation.copy(), translation.copy()
    rotation_w2c = np.swapaxes(rotation, -1, -2)
    return rotation_w2c, -np.einsum("nij,nj->ni", rotation_w2c, translation)


def read_intrinsics(spec: str, image_shape: tuple[int, int] | None = None) -> np.ndarray:
    """`fx,fy,cx,cy` (pixels) or a file with 4 numbers or a 3x3 K -> pixel-index K [3, 3].

    Args:
      spec: the numbers, or a file holding them.
      image_shape: (height, width) of the images, if known: the principal point must
        then lie inside the image.

    Raises:
      ValueError: naming `spec` when it is not 4 or 9 finite numbers, a focal length
        is not > 0 or the principal point lies outside the image.
    """
    path = Path(spec).expanduser()
    if path.is_file():
        try:
            values = np.asarray(
                [float(value) for value in path.read_text().replace(",", " ").split()], np.float64
            )
        except ValueError:
            raise ValueError(f"intrinsics file {path}: not numbers") from None
    else:
        try:
            values = np.asarray([float(value) for value in spec.split(",")], np.float64)
        except ValueError:
            raise ValueError(f"intrinsics {spec!r} is neither a file nor 'fx,fy,cx,cy'") from None
    if values.size == 4:
        fx, fy, cx, cy = values
    elif values.size == 9:
        matrix = values.reshape(3, 3)
        fx, fy, cx, cy = matrix[0, 0], matrix[1, 1], matrix[0, 2], matrix[1, 2]
    else:
        raise ValueError(f"intrinsics {spec!r}: expected 4 numbers or a 3x3 K, got {values.size}")
    if not (np.isfinite(values).all() and fx > 0 and fy > 0):
        raise ValueError(f"intrinsics {spec!r}: need finite values and fx, fy > 0")
    if image_shape is not None:
        height, width = image_shape
        if not (-0.5 <= cx <= width - 0.5 and -0.5 <= cy <= height - 0.5):
            raise ValueError(
                f"intrinsics {spec!r}: principal point ({cx}, {cy}) lies outside the "
                f"{width}x{height} images (OpenCV pixels: -0.5 to {width - 0.5}, "
                f"-0.5 to {height - 0.5}); are they for another resolution?"
            )
    return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])


def list_images(folder: str | Path) -> list[Path]:
    """The image files of a folder, in name order."""
    folder = Path(folder)
    if not folder.is_dir():
        raise FileNotFoundError(f"image folder {folder} does not exist")
    images = sorted(p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
    if not images:
        raise FileNotFoundError(f"no images ({', '.join(IMAGE_SUFFIXES)}) in {folder}")
    return images


# A time stamp as a file name: digits, optionally one '.' and digits (TUM's
# 1305031102.175304). Not Python's float(): it takes '07_1' (71), '-1', '1e5', 'nan', 'inf'.
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


def read_image(path: Path) -> np.ndarray:
    """[H, W, 3] uint8 RGB."""
    image = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if image is None:
        raise ValueError(f"cannot read image {path}")
    return cv2.cvtColor(image, cv2.COLOR_BGR2RGB)


def read_dense_depth(path: Path, scale: float) -> np.ndarray:
    """A depth image (16-bit PNG, TIFF) or `.npy` -> [H, W] float32 metres, 0 = invalid.

    0, NaN and +-inf mean "no reading" (TUM's PNGs store 0; ROS's REP 118 float images
    NaN and +-inf); a negative value is an error.

    Raises:
      ValueError: naming the file when it cannot be read, is not [H, W] or holds a
        negative depth.
    """
    if path.suffix == ".npy":
        depth = np.load(path)
    else:
        depth = cv2.imread(str(path), cv2.IMREAD_ANYDEPTH)
        if depth is None:
            raise ValueError(f"cannot read depth image {path}")
    if depth.ndim != 2:
        raise ValueError(f"depth {path} must be [H, W], got shape {depth.shape}")
    depth = depth.astype(np.float32) * np.float32(scale)
    negative = np.isfinite(depth) & (depth < 0)
    if negative.any():
        row, column = np.argwhere(negative)[0]
        raise ValueError(
            f"depth {path}: {int(negative.sum())} negative value(s), e.g. "
            f"{depth[row, column]} at (u={column}, v={row})"
        )
    return np.where(np.isfinite(depth) & (depth > 0), depth, 0.0).astype(np.float32)


def read_sparse_depth(
    csv_path: Path,
    image_paths: Sequence[Path],
    shape: tuple[int, int],
    scale: float,
    match_frames: str = "auto",
    max_time_difference: float = 0.02,
) -> list[np.ndarray]:
    """CSV `frame,u,v,depth` -> one [H, W] map per image, 0 where there is no reading.

    A row's frame is matched to an image as `match_frames` says (`reading_frame_indices`).

    Raises:
      ValueError: naming the file and line of a row whose frame is not an image, whose
        u, v or depth is not a finite number, whose pixel lies outside the image or
        whose depth is not > 0 (a frame without a reading has no row).
      ArgumentError: a frame not matched by time or order (`reading_frame_indices`).
    """
    if not csv_path.is_file():
        raise FileNotFoundError(f"range readings {csv_path} do not exist")
    height, width = shape
    rows: list[tuple[str, int, int, float]] = []
    line_numbers: list[int] = []
    with open(csv_path, newline="") as stream:
        for line_number, row in enumerate(csv.reader(stream), 1):
            if not row or row[0].strip().startswith("#"):
                continue
            if len(row) != 4:
                raise ValueError(f"{csv_path}:{line_number}: expected frame,u,v,depth, got {row}")
            try:
                u, v, depth = (float(value) for value in row[1:])
            except ValueError:
                if line_number == 1:
                    continue  # header
                raise ValueError(f"{csv_path}:{line_number}: not numbers: {row}") from None
            if not np.all(np.isfinite([u, v, depth])):
                raise ValueError(f"{csv_path}:{line_number}: NaN or infinite value in {row}")
            if depth <= 0:
                raise ValueError(
                    f"{csv_path}:{line_number}: depth {depth} is not > 0 (leave out the row "
                    "of a frame without a reading)"
                )
            column, line = int(round(u)), int(round(v))
            if not (0 <= column < width and 0 <= line < height):
                raise ValueError(
                    f"{csv_path}:{line_number}: pixel ({u}, {v}) outside the {width}x{height} image"
                )
            rows.append((row[0].strip(), column, line, depth))
            line_numbers.append(line_number)
    indices = reading_frame_indices(
        [frame for frame, *_ in rows],
        line_numbers,
        csv_path,
        image_paths,
        match_frames,
        max_time_difference,
    )
    maps = [np.zeros(shape, np.float32) for _ in image_paths]
    for index, (_, column, line, depth) in zip(indices, rows, strict=True):
        maps[index][line, column] = depth * scale
    return maps


def select_pairs(
    camera_centres: np.ndarray,
    frame_gap: int = 1,
    min_baseline: float | None = None,
    max_baseline: float | None = None,
    max_frame_gap: int = 30,
) -> list[tuple[int, int]]:
    """View pairs (i, j), j > i, from camera centres [N, 3] in world coordinates.

    Without a baseline range: (i, i + frame_gap). With one: i and the nearest later
    frame (at most `max_frame_gap` ahead) whose centre is within [min, max] metres.
    """
    if frame_gap < 1:
        raise ValueError(f"frame_gap must be >= 1, got {frame_gap}")
    count = len(camera_centres)
    if min_baseline is None and max_baseline is None:
        return [(i, i + frame_gap) for i in range(count - frame_gap)]
    low = 0.0 if min_baseline is None else min_baseline
    high = np.inf if max_baseline is None else max_baseline
    if low > high:
        raise ValueError(f"min_baseline {low} > max_baseline {high}")
    pairs = []
    for i in range(count):
        for j in range(i + 1, min(count, i + max_frame_gap + 1)):
            if low <= np.linalg.norm(camera_centres[j] - camera_centres[i]) <= high:
                pairs.append((i, j))
                break
    return pairs
