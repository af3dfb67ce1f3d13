"""A pure-Python reader of DeMoN's multi-view HDF5 files (h5py, lz4 block, WebP).

Layout (see DeMoN's `multivih5datareaderop`): every top-level group not starting
with `.` is a scene; `/<scene>/frames/t0/v<k>/{image,depth,camera}` are its views
and the `t0` attribute `viewpoint_pairs` lists the view pairs to use.

Conventions of the stored camera, as DeMoN's own reader interprets it:

* `camera` holds `[fx, fy, skew, cx, cy, R (column-major), t]` with
  `X_cam = R X_world + t`.
* K is in pixels of the view's image with the origin at the top-left *corner*
  (DeMoN's reader puts pixel (x, y) at `(x + 0.5, y + 0.5)`), which is exactly
  gld's normalised-intrinsics convention once divided by the image size, so the
  normalised intrinsics are `[fx/W, fy/H, cx/W, cy/H]` of the stored values.
  Skew is dropped (gld's cameras have none; DeMoN's files store 0).
* `ray_length` depth is converted to camera z: `z = r / ||K^-1 [x + 0.5, y + 0.5, 1]||`.

Images are decoded by `data.demon.images` (DeMoN's C++ reader's WebP decoding by
default); `check_image_decoder` refuses, before a build, files whose lossy images that
decoding cannot read here.

Damage in a view raises `damage.DamagedDataError` carrying a reason from
`damage.REASONS`, so a builder can skip the affected pair, count it and go on.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import h5py
import lz4.block
import numpy as np

from data.demon import images
from data.demon.damage import DamagedDataError
from gld import geometry

SPLITS = ("train", "test")


@dataclasses.dataclass(frozen=True)
class View:
    """One decoded viewpoint at the file's resolution.

    Attributes:
      image: [H, W, 3] uint8 RGB.
      depth: [h, w] float32 camera-z depth, 0 where invalid (usually h, w = H, W).
      intrinsics: [4] float64 normalised `[fx/W, fy/H, cx/W, cy/H]`.
      rotation, translation: [3, 3], [3] float64 world-to-camera: X_cam = R X_world + t.
      depth_metric: the file's depth metric, "camera_z" or "ray_length" (DeMoN's reader
        resamples ray lengths before converting them, see `pairs.resize_view`).
    """

    image: np.ndarray
    depth: np.ndarray
    intrinsics: np.ndarray
    rotation: np.ndarray
    translation: np.ndarray
    depth_metric: str = "camera_z"


def _text(value: Any) -> str:
    """An HDF5 string attribute (bytes, numpy bytes or str) as str."""
    if isinstance(value, np.ndarray) and value.shape == ():
        value = value[()]
    if isinstance(value, bytes | np.bytes_):
        return bytes(value).decode("ascii", errors="replace")
    return str(value)


def lossy_image_files(paths: Sequence[str | Path]) -> list[Path]:
    """The files among `paths` whose first scene group's view 0 holds a lossy WebP image
    (DeMoN's files do; the converter writes lossless ones by default). One image per
    file is read, nothing decoded."""
    lossy = []
    for path in paths:
        with h5py.File(path, "r") as h5_file:
            for group in scene_groups(h5_file):
                try:
                    image = h5_file.get(f"{group}/frames/t0/v0/image")
                    data = image[()].tobytes() if isinstance(image, h5py.Dataset) else None
                except (OSError, KeyError, RuntimeError):
                    continue  # a damaged group; the build skips and counts it
                if data is not None:
                    if images.webp_compression(data) == "lossy":
                        lossy.append(Path(path))
                    break
    return lossy


def check_image_decoder(decoder: str, paths: Sequence[str | Path]) -> None:
    """Refuses, before anything is built, to read lossy images of `paths` with the
    `demon` decoder when the `webp` package is missing.

    Raises:
      images.MissingDecoderError: one line naming the package and `--image_decoder=opencv`.
    """
    if decoder != "demon" or images.webp_decoder_available():
        return
    lossy = ", ".join(path.name for path in lossy_image_files(paths))
    if lossy:
        raise images.MissingDecoderError(images.missing_decoder_message(lossy))


def decode_depth(data: bytes, extents: Any, where: str = "depth") -> np.ndarray:
    """An LZ4-block buffer of row-major float16 -> [height, width] float32 (raw values).

    Args:
      data: the compressed bytes.
      extents: [height, width] from the dataset's `extents` attribute.
      where: names the dataset in errors.

    Raises:
      DamagedDataError: `wrong_extents` when the buffer decodes to another size,
        `corrupt_depth` when it does not decode at all (e.g. truncated).
    """
    extents = np.asarray(extents).reshape(-1)
    if extents.size != 2 or not np.issubdtype(extents.dtype, np.integer) or np.any(extents <= 0):
        raise DamagedDataError("wrong_extents", where, f"extents {extents.tolist()} not [H, W] > 0")
    height, width = int(extents[0]), int(extents[1])
    expected = 2 * height * width
    try:
        raw = lz4.block.decompress(data, uncompressed_size=expected)
    except lz4.block.LZ4BlockError:
        # A bigger buffer tells a valid stream of another size from a broken one
        # (an LZ4 block expands at most ~255 times).
        try:
            raw = lz4.block.decompress(data, uncompressed_size=255 * len(data) + 64)
        except lz4.block.LZ4BlockError:
            raise DamagedDataError(
                "corrupt_depth", where, f"LZ4 block of {len(data)} bytes does not decode"
            ) from None
    if len(raw) != expected:
        raise DamagedDataError(
            "wrong_extents",
            where,
            f"extents {[height, width]} need {expected} bytes, buffer decodes to {len(raw)}",
        )
    return np.frombuffer(raw, np.float16).reshape(height, width).astype(np.float32)


def parse_camera(values: Any, where: str = "camera") -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """DeMoN's 17 camera values -> (K [3, 3], R [3, 3], t [3]), float64.

    `[fx, fy, skew, cx, cy, r11, r21, r31, r12, r22, r32, r13, r23, r33, tx, ty, tz]`:
    R is stored column-major; X_cam = R X_world + t.
    """
    values = np.asarray(values, np.float64).reshape(-1)
    if values.size != 17:
        raise DamagedDataError("bad_camera", where, f"expected 17 values, got {values.size}")
    if not np.all(np.isfinite(values)):
        raise DamagedDataError("bad_camera", where, f"non-finite values {values.tolist()}")
    fx, fy, skew, cx, cy = values[:5]
    if fx <= 0 or fy <= 0:
        raise DamagedDataError("bad_camera", where, f"focal lengths fx={fx}, fy={fy} not > 0")
    camera_matrix = np.array([[fx, skew, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
    rotation = values[5:14].reshape(3, 3).T  # column-major storage
    orthonormality = np.abs(rotation @ rotation.T - np.eye(3)).max()
    if orthonormality > 1e-3 or np.linalg.det(rotation) < 0:
        raise DamagedDataError(
            "bad_camera", where, f"not a rotation (|R R^T - I| = {orthonormality:.2g})"
        )
    return camera_matrix, rotation, values[14:17].copy()


def normalised_intrinsics(camera_matrix: np.ndarray, height: int, width: int) -> np.ndarray:
    """DeMoN's corner-origin K of a [height, width] image -> normalised [4] (skew dropped)."""
    # gld.geometry works in pixel-index coordinates (pixel centres at integers).
    pixel_index_matrix = camera_matrix - np.array([[0, 0, 0.5], [0, 0, 0.5], [0, 0, 0]])
    return np.asarray(geometry.normalised_intrinsics(pixel_index_matrix, height, width))


def ray_norms(intrinsics: np.ndarray, height: int, width: int) -> np.ndarray:
    """[H, W] lengths of the rays through the pixel centres at unit camera z.

    Args:
      intrinsics: [4] normalised intrinsics of the camera.
      height, width: the image size the rays are taken at.
    """
    camera_matrix = geometry.intrinsics_matrix(np.asarray(intrinsics, np.float64), height, width)
    return np.linalg.norm(geometry.backproject(np.ones((height, width)), camera_matrix), axis=-1)


def ray_length_to_camera_z(ray_length: np.ndarray, intrinsics: np.ndarray) -> np.ndarray:
    """Distance along each pixel's ray [H, W] -> camera-z depth [H, W].

    Args:
      ray_length: [H, W] distances from the camera centre.
      intrinsics: [4] normalised intrinsics of the camera.
    """
    return (ray_length / ray_norms(intrinsics, *ray_length.shape)).astype(np.float32)


def _dataset(group: h5py.Group, name: str, reason: str, where: str) -> h5py.Dataset:
    item = group.get(name)
    if not isinstance(item, h5py.Dataset):
        raise DamagedDataError(reason, f"{where}/{name}", "dataset missing")
    return item


def read_view(
    view_group: h5py.Group, where: str, image_decoder: str = images.DEFAULT_IMAGE_DECODER
) -> View:
    """Reads and validates `/<scene>/frames/t0/v<k>` -> View (depth converted to camera z).

    `image_decoder` is one of `images.IMAGE_DECODERS`.

    Raises:
      DamagedDataError naming `where` and the reason.
    """
    image_dataset = _dataset(view_group, "image", "corrupt_image", where)
    image_format = _text(image_dataset.attrs.get("format", "webp"))
    if image_format != "webp":
        raise DamagedDataError("corrupt_image", f"{where}/image", f"format {image_format!r}")
    image = images.decode_image(image_dataset[()].tobytes(), f"{where}/image", image_decoder)

    camera_dataset = _dataset(view_group, "camera", "missing_camera", where)
    camera_format = _text(camera_dataset.attrs.get("format", "pinhole"))
    if camera_format != "pinhole":
        raise DamagedDataError("bad_camera", f"{where}/camera", f"format {camera_format!r}")
    camera_matrix, rotation, translation = parse_camera(camera_dataset[()], f"{where}/camera")
    intrinsics = normalised_intrinsics(camera_matrix, *image.shape[:2])

    depth_dataset = _dataset(view_group, "depth", "corrupt_depth", where)
    depth_where = f"{where}/depth"
    depth_format = _text(depth_dataset.attrs.get("format", "lz4half"))
    if depth_format != "lz4half":
        raise DamagedDataError("corrupt_depth", depth_where, f"format {depth_format!r}")
    if "extents" not in depth_dataset.attrs:
        raise DamagedDataError("wrong_extents", depth_where, "no extents attribute")
    depth = decode_depth(depth_dataset[()].tobytes(), depth_dataset.attrs["extents"], depth_where)
    metric = _text(depth_dataset.attrs.get("depth_metric", "camera_z"))
    valid = geometry.valid_depth(depth)
    depth = np.where(valid, depth, 0.0).astype(np.float32)
    if metric == "ray_length":
        depth = np.where(valid, ray_length_to_camera_z(depth, intrinsics), 0.0)
    elif metric != "camera_z":
        raise DamagedDataError("corrupt_depth", depth_where, f"unknown depth_metric {metric!r}")
    if not valid.any():
        raise DamagedDataError(
            "invalid_depth", depth_where, "no finite, positive value (all NaN, inf or <= 0)"
        )
    return View(image, depth.astype(np.float32), intrinsics, rotation, translation, metric)


def scene_groups(h5_file: h5py.File) -> list[str]:
    """Names of the scene groups, sorted; reserved `.`-groups are not scenes."""
    return sorted(name for name in h5_file.keys() if not name.startswith("."))


def demon_order(groups: Sequence[str]) -> list[str]:
    """Scene groups in the order DeMoN's reader op visits them in its test phase: it
    sorts a file's groups by name and takes them from the back, so reverse-sorted."""
    return sorted(groups, reverse=True)


def view_count(t0_group: h5py.Group) -> int:
    """Number of consecutive viewpoints v0, v1, ... in a `frames/t0` group."""
    count = 0
    while f"v{count}" in t0_group:
        count += 1
    return count


def viewpoint_pairs(t0_group: h5py.Group, split: str, where: str = "t0") -> list[tuple[int, int]]:
    """The view pairs of a scene, as DeMoN's reader selects them.

    train: every pair listed in `viewpoint_pairs` (all ordered pairs if absent);
    test: exactly the first listed pair ((0, 1) if absent).

    Raises:
      DamagedDataError (`too_few_views`, `bad_viewpoint_pairs`).
    """
    if split not in SPLITS:
        raise ValueError(f"split must be one of {SPLITS}, got {split!r}")
    num_views = view_count(t0_group)
    if num_views < 2:
        raise DamagedDataError("too_few_views", where, f"{num_views} viewpoint(s)")
    if "viewpoint_pairs" in t0_group.attrs:
        flat = np.asarray(t0_group.attrs["viewpoint_pairs"]).reshape(-1)
        if flat.size == 0 or flat.size % 2 or not np.issubdtype(flat.dtype, np.integer):
            raise DamagedDataError(
                "bad_viewpoint_pairs",
                where,
                f"viewpoint_pairs {flat.tolist()} is not [i j i j ...]",
            )
        pairs = [(int(first), int(second)) for first, second in flat.reshape(-1, 2)]
    else:
        pairs = [(i, j) for i in range(num_views) for j in range(num_views) if i != j]
    return pairs[:1] if split == "test" else pairs


def file_problem(path: str | Path) -> str | None:
    """Why `path` cannot be a DeMoN file, judged from its HDF5 structure alone; None if
    it can. Nothing is decoded: the file opens (a truncated HDF5 file does not), has
    scene groups, and one of them has `frames/t0/v0` with image, depth and camera.
    Damage inside single groups is left to the build, which skips and counts it."""
    path = Path(path)
    if not path.is_file():
        return "does not exist"
    try:
        with h5py.File(path, "r") as h5_file:
            groups = scene_groups(h5_file)
            if not groups:
                return "holds no scene groups"
            for group in groups:
                try:
                    view = h5_file.get(f"{group}/frames/t0/v0")
                    if isinstance(view, h5py.Group) and all(
                        isinstance(view.get(name), h5py.Dataset)
                        for name in ("image", "depth", "camera")
                    ):
                        return None
                except (OSError, KeyError, RuntimeError):
                    continue  # a damaged group; the build skips and counts it
            return (
                f"none of its {len(groups)} scene groups has frames/t0/v0 with image, "
                "depth and camera"
            )
    except (OSError, KeyError, RuntimeError) as error:
        return f"is not a readable HDF5 file ({error})"


def check_files(paths: Sequence[str | Path]) -> None:
    """Checks every file with `file_problem`.

    Raises:
      ValueError: naming every file that cannot be a DeMoN file, and why.
    """
    problems = [(path, file_problem(path)) for path in paths]
    problems = [f"{path} {problem}" for path, problem in problems if problem]
    if problems:
        raise ValueError(
            f"{len(problems)} of {len(paths)} DeMoN file(s) unusable:\n  "
            + "\n  ".join(problems)
            + "\nDownload or convert them again."
        )


class DemonFile:
    """An open DeMoN HDF5 file: scene groups, their view pairs and decoded views.

    Use as a context manager. Views are decoded on demand and cached per scene,
    so a training group with many pairs decodes each view once. `image_decoder` is
    one of `images.IMAGE_DECODERS`, or None for DeMoN's.
    """

    def __init__(self, path: str | Path, image_decoder: str | None = None):
        self.image_decoder = images.resolve_image_decoder(image_decoder)
        self.path = Path(path)
        if not self.path.is_file():
            raise FileNotFoundError(f"DeMoN file {self.path} does not exist")
        try:
            self._file = h5py.File(self.path, "r")
        except OSError as error:
            raise ValueError(f"{self.path} is not a readable HDF5 file: {error}") from None
        self._cache_group: str | None = None
        self._cache: dict[int, View | DamagedDataError] = {}

    @property
    def name(self) -> str:
        return self.path.name

    def close(self) -> None:
        self._file.close()

    def __enter__(self) -> DemonFile:
        return self

    def __exit__(self, *exc_info) -> None:
        self.close()

    def groups(self) -> list[str]:
        """Scene group names, sorted, without reserved `.`-groups."""
        return scene_groups(self._file)

    def _t0(self, group: str) -> h5py.Group:
        t0 = self._file.get(f"{group}/frames/t0")
        if not isinstance(t0, h5py.Group):
            raise DamagedDataError("too_few_views", f"{self.name}/{group}", "no frames/t0 group")
        return t0

    def pairs(self, group: str, split: str) -> list[tuple[int, int]]:
        """The view pairs of a scene group for a split (see `viewpoint_pairs`)."""
        where = f"{self.name}/{group}"
        try:
            return viewpoint_pairs(self._t0(group), split, where)
        except (OSError, KeyError, RuntimeError) as error:
            raise DamagedDataError("unreadable_group", where, str(error)) from None

    def view(self, group: str, index: int) -> View:
        """View `v<index>` of a scene group; damage raises DamagedDataError (also when cached)."""
        if group != self._cache_group:
            self._cache_group, self._cache = group, {}
        if index not in self._cache:
            self._cache[index] = self._read_view(group, index)
        result = self._cache[index]
        if isinstance(result, DamagedDataError):
            raise result
        return result

    def _read_view(self, group: str, index: int) -> View | DamagedDataError:
        where = f"{self.name}/{group}/frames/t0/v{index}"
        try:
            view_group = self._t0(group).get(f"v{index}")
            if not isinstance(view_group, h5py.Group):
                return DamagedDataError("bad_viewpoint_pairs", where, "no such viewpoint")
            return read_view(view_group, where, self.image_decoder)
        except DamagedDataError as error:
            return error
        except (OSError, KeyError, RuntimeError) as error:
            return DamagedDataError("unreadable_group", where, str(error))


def example_id(file_name: str, group: str, pair: tuple[int, int]) -> str:
    """`"<file name>/<group>/<i>-<j>"`, the id that traces an example back to its source."""
    return f"{file_name}/{group}/{pair[0]}-{pair[1]}"
