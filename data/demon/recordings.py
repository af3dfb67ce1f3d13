"""A robot's recording, read frame by frame: images, trajectory, intrinsics, depth, pairs.

Readers of what `python -m data.demon.convert` takes (its docstring describes the
formats): TUM trajectories and 4x4 pose matrices turned into DeMoN's world-to-camera
poses, intrinsics in OpenCV pixels, images, dense depth images and sparse range
readings. Poses, depth images and range readings are matched to the images as
`--match_frames` says (`MATCH_FRAMES`), and `select_pairs` chooses the frame pairs to
write.

Frames are matched by `data.demon.frame_matching` (re-exported here: the predictor reads
a recording through this module, `gld.inference.recording_run.RecordingFiles`).
"""

from __future__ import annotations

import csv
from collections.abc import Sequence
from pathlib import Path

import cv2
import numpy as np

from data.demon.frame_matching import (  # noqa: F401  (the recording's readers, in one place)
    DEPTH_SUFFIXES,
    MATCH_FRAMES,
    associate_depth_files,
    associate_poses,
    check_match_frames,
    reading_frame_indices,
    time_stamp,
)

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".webp", ".ppm")
POSE_FORMATS = ("tum", "matrix")
POSE_DIRECTIONS = ("camera_to_world", "world_to_camera")
DEPTH_METRICS = ("camera_z", "ray_length")


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
