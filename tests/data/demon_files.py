"""Writes tiny DeMoN-format HDF5 files byte by byte for the tests, independently of data.demon.

Images are lossless WebP unless a quality is given (so a read-back image equals what
was written), depth is an LZ4 block of row-major float16 with `extents`, the camera is
the 17-value vector with a column-major rotation and K in corner-origin pixel coordinates.
"""

from __future__ import annotations

from typing import Any

import cv2
import h5py
import lz4.block
import numpy as np


def rotation_about(axis: Any, degrees: float) -> np.ndarray:
    """[3, 3] rotation by `degrees` about `axis` (Rodrigues, written out)."""
    axis = np.asarray(axis, np.float64) / np.linalg.norm(axis)
    angle = np.radians(degrees)
    cross = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(angle) * cross + (1 - np.cos(angle)) * cross @ cross


def camera_values(camera_matrix: np.ndarray, rotation: np.ndarray, translation: Any) -> np.ndarray:
    """[fx, fy, skew, cx, cy, r11, r21, r31, r12, r22, r32, r13, r23, r33, tx, ty, tz]."""
    k = camera_matrix
    column_major = [rotation[row, col] for col in range(3) for row in range(3)]
    return np.array(
        [k[0, 0], k[1, 1], k[0, 1], k[0, 2], k[1, 2], *column_major, *translation], np.float64
    )


def webp_bytes(image_rgb: np.ndarray, quality: int = 101) -> bytes:
    """WebP bytes of an [H, W, 3] uint8 RGB image: lossless at quality 101, else lossy."""
    ok, data = cv2.imencode(
        ".webp", cv2.cvtColor(image_rgb, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_WEBP_QUALITY, quality]
    )
    assert ok
    return data.tobytes()


def lz4_depth_bytes(depth: np.ndarray) -> bytes:
    """LZ4 block (no size header) of the float16 depth, row-major."""
    return lz4.block.compress(np.ascontiguousarray(depth, np.float16).tobytes(), store_size=False)


def ray_norms(camera_matrix: np.ndarray, height: int, width: int) -> np.ndarray:
    """[H, W] ||K^-1 [x + 0.5, y + 0.5, 1]|| with K in corner-origin pixels."""
    y, x = np.mgrid[0:height, 0:width].astype(np.float64)
    rays = np.stack([x + 0.5, y + 0.5, np.ones_like(x)], axis=-1) @ np.linalg.inv(camera_matrix).T
    return np.linalg.norm(rays, axis=-1)


def texture(rng: np.random.Generator, height: int, width: int) -> np.ndarray:
    """[H, W, 3] uint8 smooth random texture (something optical flow can track)."""
    coarse = rng.integers(0, 256, size=(max(height // 8, 2), max(width // 8, 2), 3), dtype=np.uint8)
    return cv2.resize(coarse, (width, height), interpolation=cv2.INTER_CUBIC)


def make_view(
    rng: np.random.Generator,
    height: int,
    width: int,
    rotation: np.ndarray,
    translation: Any,
    camera_matrix: np.ndarray | None = None,
) -> dict[str, Any]:
    """A view dict: image, depth (camera z, metres), camera_matrix, rotation, translation."""
    if camera_matrix is None:
        camera_matrix = np.array(
            [
                [0.89 * width, 0.0, 0.5 * width + 3.0],
                [0.0, 1.19 * height, 0.5 * height - 2.0],
                [0.0, 0.0, 1.0],
            ]
        )
    y, x = np.mgrid[0:height, 0:width].astype(np.float32)
    depth = 2.0 + x / width + 0.5 * y / height + rng.uniform(0, 0.1, size=(height, width))
    return {
        "image": texture(rng, height, width),
        "depth": depth.astype(np.float32),
        "camera_matrix": camera_matrix,
        "rotation": np.asarray(rotation, np.float64),
        "translation": np.asarray(translation, np.float64),
    }


def moving_views(rng: np.random.Generator, count: int, height: int, width: int) -> list[dict]:
    """`count` views with distinct, non-symmetric rotations and translations."""
    return [
        make_view(
            rng,
            height,
            width,
            rotation_about([0.3, 1.0, 0.2 * index], 2.0 + 3.0 * index),
            [0.1 * index + 0.05, -0.04 * index, 0.3 + 0.02 * index],
        )
        for index in range(count)
    ]


def write_view(
    view_group: h5py.Group,
    view: dict[str, Any],
    *,
    depth_metric: str = "camera_z",
    image_data: bytes | None = None,
    depth_data: bytes | None = None,
    extents: Any = None,
    camera: bool = True,
) -> None:
    """Writes image / depth / camera of a view; the overrides produce damaged data."""
    image_data = webp_bytes(view["image"]) if image_data is None else image_data
    image = view_group.create_dataset("image", data=np.frombuffer(image_data, np.int8))
    image.attrs["format"] = np.bytes_("webp")
    depth_values = view["depth"]
    if depth_metric == "ray_length":
        depth_values = depth_values * ray_norms(view["camera_matrix"], *depth_values.shape)
    depth_data = lz4_depth_bytes(depth_values) if depth_data is None else depth_data
    depth = view_group.create_dataset("depth", data=np.frombuffer(depth_data, np.int8))
    depth.attrs["format"] = np.bytes_("lz4half")
    depth.attrs["extents"] = np.asarray(
        view["depth"].shape if extents is None else extents, np.int32
    )
    depth.attrs["depth_metric"] = np.bytes_(depth_metric)
    if camera:
        values = camera_values(view["camera_matrix"], view["rotation"], view["translation"])
        dataset = view_group.create_dataset("camera", data=values)
        dataset.attrs["format"] = np.bytes_("pinhole")


def write_scene(
    h5_file: h5py.File,
    name: str,
    views: list[dict[str, Any]],
    viewpoint_pairs: Any = (0, 1),
    view_options: dict[int, dict[str, Any]] | None = None,
) -> None:
    """Writes `/<name>/frames/t0/v<k>` per view; `viewpoint_pairs=None` omits the attribute."""
    t0 = h5_file.create_group(f"{name}/frames/t0")
    if viewpoint_pairs is not None:
        t0.attrs["viewpoint_pairs"] = np.asarray(viewpoint_pairs, np.int32)
    for index, view in enumerate(views):
        write_view(t0.create_group(f"v{index}"), view, **(view_options or {}).get(index, {}))
