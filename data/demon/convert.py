r"""Converts a robot's recording into a DeMoN-format HDF5 file for the `demon/custom` config.

    python -m data.demon.convert --images=rec/rgb --poses=rec/groundtruth.txt \
        --intrinsics=517.3,516.5,318.6,255.3 --depth=rec/range.csv \
        --output_dir=~/demon --test_fraction=0.2

then `python -m experiments.train --dataset=demon/custom --manual_dir=~/demon`.

Inputs
* `--images`: a folder of images (PNG, JPEG, ...), in name order = time order.
* `--poses`: `--pose_format=tum`: the TUM trajectory format, one line
  `timestamp tx ty tz qx qy qz qw` per pose, camera-to-world (the camera's position
  and orientation in the world, as TUM defines it). Images named by their timestamp
  (TUM's `1305031102.175304.png`) are matched to the nearest pose within
  `--max_time_difference` seconds; otherwise the i-th pose belongs to the i-th image.
  `--pose_format=matrix`: a `.npy` [N, 4, 4] or a text file with one row-major 4x4
  per line (16 numbers, or 17 with a leading timestamp), in the i-th-image order;
  `--pose_direction` says whether they map camera to world (default, what SLAM
  systems export) or world to camera (`X_cam = R X_world + t`, DeMoN's convention).
* `--intrinsics`: `fx,fy,cx,cy` in pixels, or a file with those 4 numbers or a 3x3 K
  (skew is dropped), in OpenCV's convention: pixel (0, 0) has its centre at (0, 0).
  (DeMoN stores the principal point with the origin at the top-left corner; the
  converter adds the half pixel.)
* `--depth` (`--depth_scale` metres per stored unit, `--depth_metric` camera_z or
  ray_length): a folder of dense depth images named like the images (16-bit PNG,
  0 = no reading, e.g. TUM's with scale 0.0002) or `.npy` arrays; or a CSV
  `frame,u,v,depth` of sparse range readings (a single-pixel range sensor: every
  other pixel is invalid), `frame` being the image's name without extension or its
  index in name order, `u, v` pixel coordinates in the image (rounded). A range
  sensor measures along its beam: pass `--depth_metric=ray_length` if it does.

Pairs: frame i with frame i + `--frame_gap`; with `--min_baseline` / `--max_baseline`
(metres) instead frame i with the nearest later frame (at most `--max_frame_gap`
ahead) whose camera centre lies in that distance range. Pairs whose frames have no
depth reading are left out (and counted).

Output: `<output_dir>/custom_<split>.h5` (`custom_<split>_<recording>.h5` with
`--recording`), one scene group per pair (`<frame1>__<frame2>`, two views,
`viewpoint_pairs = [0 1]`), so the builder's train and test splits see every pair.
`--test_fraction` holds out the last frames of the recording as the test split
(pairs across the boundary are dropped, so no test frame is seen in training).
Images are WebP (lossless by default), depth float16 LZ4 blocks.
"""

from __future__ import annotations

import collections
import csv
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import cv2
import h5py
import lz4.block
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


def output_path(output_dir: str | Path, split: str, recording: str | None = None) -> Path:
    """`custom_<split>.h5` or `custom_<split>_<recording>.h5`, the names `demon/custom` reads."""
    suffix = f"_{recording}" if recording else ""
    return Path(output_dir).expanduser() / f"custom_{split}{suffix}.h5"


def convert(
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
) -> dict[str, Any]:
    """Writes a recording as DeMoN-format file(s); see the module docstring for the inputs.

    Returns:
      {"files": {split: path}, "pairs": {split: count}, "dropped": {reason: count}}.
    """
    if pose_format not in POSE_FORMATS:
        raise ValueError(f"pose_format must be one of {POSE_FORMATS}, got {pose_format!r}")
    if depth_metric not in DEPTH_METRICS:
        raise ValueError(f"depth_metric must be one of {DEPTH_METRICS}, got {depth_metric!r}")
    if split not in ("train", "test"):
        raise ValueError(f"split must be 'train' or 'test', got {split!r}")
    if not 0.0 <= test_fraction < 1.0:
        raise ValueError(f"test_fraction must be in [0, 1), got {test_fraction}")
    image_paths = list_images(images)
    if pose_format == "tum":
        timestamps, camera_to_world = read_tum_trajectory(poses)
        rotations, translations = world_to_camera(camera_to_world, "camera_to_world")
    else:
        timestamps = None
        rotations, translations = world_to_camera(read_pose_matrices(poses), pose_direction)
    pose_index = associate_poses(image_paths, timestamps, len(rotations), max_time_difference)
    rotations, translations = rotations[pose_index], translations[pose_index]
    camera_matrix = read_intrinsics(str(intrinsics))
    centres = -np.einsum("nji,nj->ni", rotations, translations)  # -R^T t

    first_image = read_image(image_paths[0])
    depth_path = Path(depth).expanduser()
    if depth_path.is_dir():
        depth_maps = None
        depth_files = associate_depth_files(depth_path, image_paths, max_time_difference)
    elif depth_path.suffix.lower() == ".csv":
        depth_maps = read_sparse_depth(depth_path, image_paths, first_image.shape[:2], depth_scale)
    else:
        raise FileNotFoundError(f"depth {depth_path} is neither a folder nor a .csv file")

    def frame_depth(index: int) -> np.ndarray:
        if depth_maps is not None:
            return depth_maps[index]
        return read_dense_depth(depth_files[index], depth_scale)

    candidate_pairs = select_pairs(centres, frame_gap, min_baseline, max_baseline, max_frame_gap)
    dropped: collections.Counter = collections.Counter()
    first_test_frame = int(np.ceil(len(image_paths) * (1.0 - test_fraction)))
    split_pairs: dict[str, list[tuple[int, int]]] = {}
    for pair in candidate_pairs:
        if test_fraction == 0.0:
            split_pairs.setdefault(split, []).append(pair)
        elif pair[1] < first_test_frame:
            split_pairs.setdefault("train", []).append(pair)
        elif pair[0] >= first_test_frame:
            split_pairs.setdefault("test", []).append(pair)
        else:
            dropped["crosses_split_boundary"] += 1

    files, counts = {}, {}
    for split_name, pair_list in split_pairs.items():
        path = output_path(output_dir, split_name, recording)
        path.parent.mkdir(parents=True, exist_ok=True)
        written = 0
        with h5py.File(path, "w") as h5_file:
            h5_file.create_group(".config").attrs["source"] = np.bytes_(str(Path(images)))
            for i, j in pair_list:
                depths = {index: frame_depth(index) for index in (i, j)}
                if not all(np.any(depth_map > 0) for depth_map in depths.values()):
                    dropped["no_depth_reading"] += 1
                    continue
                group_name = f"{image_paths[i].stem}__{image_paths[j].stem}"
                t0 = h5_file.create_group(f"{group_name}/frames/t0")
                t0.attrs["viewpoint_pairs"] = np.array([0, 1], np.int32)
                t0.attrs["frames"] = np.array([image_paths[i].name, image_paths[j].name], "S")
                for view_index, frame in enumerate((i, j)):
                    image = first_image if frame == 0 else read_image(image_paths[frame])
                    if image.shape != first_image.shape:
                        raise ValueError(
                            f"{image_paths[frame]} is {image.shape}, the first image "
                            f"{first_image.shape}; all images need one size and one camera"
                        )
                    write_view(
                        t0.create_group(f"v{view_index}"),
                        image,
                        depths[frame],
                        demon_camera(camera_matrix, rotations[frame], translations[frame]),
                        depth_metric,
                        webp_quality,
                    )
                written += 1
        files[split_name], counts[split_name] = path, written
    return {"files": files, "pairs": counts, "dropped": dict(dropped)}


def main(argv: Sequence[str]) -> None:
    from absl import flags

    del argv
    values = flags.FLAGS
    result = convert(
        values.images,
        values.poses,
        values.intrinsics,
        values.output_dir,
        depth=values.depth,
        pose_format=values.pose_format,
        pose_direction=values.pose_direction,
        depth_scale=values.depth_scale,
        depth_metric=values.depth_metric,
        frame_gap=values.frame_gap,
        min_baseline=values.min_baseline,
        max_baseline=values.max_baseline,
        max_frame_gap=values.max_frame_gap,
        test_fraction=values.test_fraction,
        split=values.split,
        recording=values.recording,
        webp_quality=values.webp_quality,
        max_time_difference=values.max_time_difference,
    )
    for split_name, path in result["files"].items():
        print(f"{path}: {result['pairs'][split_name]} pairs ({split_name})")
    for reason, count in result["dropped"].items():
        print(f"pairs left out, {reason}: {count}")


def _define_flags() -> None:
    # Defined only when run as a program, so importing this module registers no flags.
    from absl import flags

    flags.DEFINE_string("images", None, "Folder of images, in name order.", required=True)
    flags.DEFINE_string("poses", None, "Trajectory file (see --pose_format).", required=True)
    flags.DEFINE_string("intrinsics", None, "fx,fy,cx,cy in pixels, or a file.", required=True)
    flags.DEFINE_string(
        "depth", None, "Folder of depth images, or frame,u,v,depth CSV.", required=True
    )
    flags.DEFINE_string("output_dir", None, "Where custom_<split>.h5 go.", required=True)
    flags.DEFINE_enum("pose_format", "tum", POSE_FORMATS, "TUM lines or 4x4 matrices.")
    flags.DEFINE_enum(
        "pose_direction", "camera_to_world", POSE_DIRECTIONS, "What --pose_format=matrix poses map."
    )
    flags.DEFINE_float("depth_scale", 1.0, "Metres per stored depth unit (TUM PNG: 0.0002).")
    flags.DEFINE_enum("depth_metric", "camera_z", DEPTH_METRICS, "z, or distance along the ray.")
    flags.DEFINE_integer("frame_gap", 1, "Pair frame i with frame i + frame_gap.")
    flags.DEFINE_float("min_baseline", None, "Metres; pairs by baseline range instead.")
    flags.DEFINE_float("max_baseline", None, "Metres; pairs by baseline range instead.")
    flags.DEFINE_integer("max_frame_gap", 30, "Farthest partner searched by baseline.")
    flags.DEFINE_float("test_fraction", 0.0, "Last share of frames written as the test split.")
    flags.DEFINE_enum("split", "train", ("train", "test"), "Split when test_fraction is 0.")
    flags.DEFINE_string("recording", None, "Name suffix: custom_<split>_<recording>.h5.")
    flags.DEFINE_integer("webp_quality", 101, "WebP quality; > 100 is lossless.")
    flags.DEFINE_float("max_time_difference", 0.02, "Seconds between image and pose stamps.")


if __name__ == "__main__":
    from absl import app

    _define_flags()
    app.run(main)
