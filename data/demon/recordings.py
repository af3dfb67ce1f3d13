"""A robot's recording, read frame by frame: images, trajectory, intrinsics, depth, pairs.

Readers of what `python -m data.demon.convert` takes (its docstring describes the
formats): TUM trajectories and 4x4 pose matrices turned into DeMoN's world-to-camera
poses, intrinsics in OpenCV pixels, images, dense depth images and sparse range
readings. Poses and depth images are matched to the images by name, time stamp or
order, and `select_pairs` chooses the frame pairs to write.
"""

from __future__ import annotations

import csv
from collections.abc import Sequence
from pathlib import Path

import cv2
import numpy as np

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".webp", ".ppm")
DEPTH_SUFFIXES = (".png", ".npy", ".tif", ".tiff")
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


def _numeric_rows(path: Path, widths: Sequence[int]) -> np.ndarray:
    """Whitespace/comma separated numbers, one record per line, `#` comments skipped."""
    rows = []
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
        rows.append(values)
    if not rows or len({len(row) for row in rows}) != 1:
        raise ValueError(f"{path}: no records, or records of different lengths")
    return np.asarray(rows, np.float64)


def read_tum_trajectory(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """TUM `timestamp tx ty tz qx qy qz qw` lines -> timestamps [N], camera-to-world [N, 4, 4]."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"trajectory {path} does not exist")
    rows = _numeric_rows(path, (8,))
    camera_to_world = np.tile(np.eye(4), (len(rows), 1, 1))
    try:
        camera_to_world[:, :3, :3] = quaternion_to_rotation(rows[:, 4:8])
    except ValueError as error:
        raise ValueError(f"{path}: {error}") from None
    camera_to_world[:, :3, 3] = rows[:, 1:4]
    return rows[:, 0], camera_to_world


def read_pose_matrices(path: str | Path) -> np.ndarray:
    """`.npy` [N, 4, 4] or text lines of 16 (or timestamp + 16) numbers -> [N, 4, 4]."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"pose file {path} does not exist")
    if path.suffix == ".npy":
        matrices = np.load(path).astype(np.float64)
    else:
        rows = _numeric_rows(path, (16, 17))
        matrices = rows[:, -16:].reshape(-1, 4, 4)
    if matrices.ndim != 3 or matrices.shape[1:] != (4, 4):
        raise ValueError(f"{path}: expected [N, 4, 4] poses, got shape {matrices.shape}")
    if not np.all(np.isfinite(matrices)):
        raise ValueError(f"{path}: poses contain NaN or inf")
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


def read_intrinsics(spec: str) -> np.ndarray:
    """`fx,fy,cx,cy` (pixels) or a file with 4 numbers or a 3x3 K -> pixel-index K [3, 3]."""
    path = Path(spec).expanduser()
    if path.is_file():
        values = np.asarray(path.read_text().replace(",", " ").split(), np.float64)
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
    if not (np.isfinite([fx, fy, cx, cy]).all() and fx > 0 and fy > 0):
        raise ValueError(f"intrinsics {spec!r}: need finite values and fx, fy > 0")
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


def _times(paths: Sequence[Path]) -> np.ndarray | None:
    """File names as timestamps (TUM names files by time), or None if any is not a number."""
    try:
        return np.array([float(path.stem) for path in paths])
    except ValueError:
        return None


def _nearest_in_time(
    query_times: np.ndarray,
    reference_times: np.ndarray,
    max_time_difference: float,
    query_paths: Sequence[Path],
) -> np.ndarray:
    """Index into `reference_times` [M] of the nearest time to each query time [N]."""
    order = np.argsort(reference_times)
    sorted_times = reference_times[order]
    right = np.clip(np.searchsorted(sorted_times, query_times), 0, len(sorted_times) - 1)
    left = np.clip(right - 1, 0, len(sorted_times) - 1)
    use_left = np.abs(query_times - sorted_times[left]) <= np.abs(sorted_times[right] - query_times)
    nearest = np.where(use_left, left, right)
    gaps = np.abs(sorted_times[nearest] - query_times)
    if np.any(gaps > max_time_difference):
        worst = int(np.argmax(gaps))
        raise ValueError(
            f"{query_paths[worst]} is {gaps[worst]:.3f} s from the nearest time stamp "
            f"(max_time_difference={max_time_difference})"
        )
    return order[nearest]


def associate_poses(
    image_paths: Sequence[Path],
    timestamps: np.ndarray | None,
    num_poses: int,
    max_time_difference: float,
) -> np.ndarray:
    """Pose index of every image [N]: nearest timestamp when names are times, else the order."""
    image_times = _times(image_paths)
    if timestamps is not None and image_times is not None:
        return _nearest_in_time(image_times, timestamps, max_time_difference, image_paths)
    if num_poses != len(image_paths):
        raise ValueError(
            f"{len(image_paths)} images but {num_poses} poses; name images by timestamp or "
            "give one pose per image"
        )
    return np.arange(len(image_paths))


def associate_depth_files(
    folder: Path, image_paths: Sequence[Path], max_time_difference: float
) -> list[Path]:
    """The depth file of every image: same name, else nearest time stamp, else the order."""
    depth_paths = sorted(p for p in folder.iterdir() if p.suffix.lower() in DEPTH_SUFFIXES)
    if not depth_paths:
        raise FileNotFoundError(f"no depth images ({', '.join(DEPTH_SUFFIXES)}) in {folder}")
    by_stem = {path.stem: path for path in depth_paths}
    if all(path.stem in by_stem for path in image_paths):
        return [by_stem[path.stem] for path in image_paths]
    image_times, depth_times = _times(image_paths), _times(depth_paths)
    if image_times is not None and depth_times is not None:
        nearest = _nearest_in_time(image_times, depth_times, max_time_difference, image_paths)
        return [depth_paths[index] for index in nearest]
    if len(depth_paths) != len(image_paths):
        raise ValueError(
            f"{len(image_paths)} images but {len(depth_paths)} depth images in {folder}; "
            "name them like the images, by time stamp, or give one per image"
        )
    return depth_paths


def read_image(path: Path) -> np.ndarray:
    """[H, W, 3] uint8 RGB."""
    image = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if image is None:
        raise ValueError(f"cannot read image {path}")
    return cv2.cvtColor(image, cv2.COLOR_BGR2RGB)


def read_dense_depth(path: Path, scale: float) -> np.ndarray:
    """A depth image (16-bit PNG, TIFF) or `.npy` -> [H, W] float32 metres, 0 = invalid."""
    if path.suffix == ".npy":
        depth = np.load(path)
    else:
        depth = cv2.imread(str(path), cv2.IMREAD_ANYDEPTH)
        if depth is None:
            raise ValueError(f"cannot read depth image {path}")
    if depth.ndim != 2:
        raise ValueError(f"depth {path} must be [H, W], got shape {depth.shape}")
    depth = depth.astype(np.float32) * scale
    return np.where(np.isfinite(depth) & (depth > 0), depth, 0.0).astype(np.float32)


def read_sparse_depth(
    csv_path: Path, image_paths: Sequence[Path], shape: tuple[int, int], scale: float
) -> list[np.ndarray]:
    """CSV `frame,u,v,depth` -> one [H, W] map per image, 0 where there is no reading."""
    if not csv_path.is_file():
        raise FileNotFoundError(f"range readings {csv_path} do not exist")
    height, width = shape
    index_of = {path.stem: index for index, path in enumerate(image_paths)}
    maps = [np.zeros(shape, np.float32) for _ in image_paths]
    with open(csv_path, newline="") as stream:
        for line_number, row in enumerate(csv.reader(stream), 1):
            if not row or row[0].strip().startswith("#"):
                continue
            if len(row) != 4:
                raise ValueError(f"{csv_path}:{line_number}: expected frame,u,v,depth, got {row}")
            frame = row[0].strip()
            try:
                u, v, depth = (float(value) for value in row[1:])
            except ValueError:
                if line_number == 1:
                    continue  # header
                raise ValueError(f"{csv_path}:{line_number}: not numbers: {row}") from None
            index = index_of.get(frame)
            if index is None and frame.isdigit() and int(frame) < len(image_paths):
                index = int(frame)
            if index is None:
                raise ValueError(f"{csv_path}:{line_number}: frame {frame!r} is not an image")
            column, line = int(round(u)), int(round(v))
            if not (0 <= column < width and 0 <= line < height):
                raise ValueError(
                    f"{csv_path}:{line_number}: pixel ({u}, {v}) outside the {width}x{height} image"
                )
            if np.isfinite(depth) and depth > 0:
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
