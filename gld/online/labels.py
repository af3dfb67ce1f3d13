"""A frame's labelled pixels from range readings: its own, and earlier frames' carried
into it by the odometry (`OnlineSettings.reading_memory`), one label a pixel.

    point = reading_point(frame)                        # a reading's world point
    labels = carried_labels(frame, points, height, width)
    labels = first_per_pixel(np.concatenate([own, labels]))
"""

from __future__ import annotations

import numpy as np

from gld import geometry
from gld.online.stream import Frame


def first_per_pixel(labels: np.ndarray) -> np.ndarray:
    """[N, 3] labels less those of a pixel labelled earlier in the array."""
    _, first = np.unique(labels[:, :2], axis=0, return_index=True)
    return labels[np.sort(first)]


def reading_point(frame: Frame) -> np.ndarray | None:
    """The world point of `frame`'s range reading, placed by its odometry (None without
    a reading). The reading is camera-z metres at pixel (u, v)."""
    if frame.reading is None:
        return None
    height, width = frame.image.shape[:2]
    camera_matrix = geometry.intrinsics_matrix(
        np.asarray(frame.intrinsics, np.float64), height, width
    )
    u, v, depth = frame.reading
    camera = depth * np.linalg.solve(camera_matrix, np.array([u, v, 1.0]))
    rotation = np.asarray(frame.rotation, np.float64)
    return rotation.T @ (camera - np.asarray(frame.translation, np.float64))


def carried_labels(frame: Frame, points: np.ndarray, height: int, width: int) -> np.ndarray:
    """[N, 3] (row, column, camera-z metres) of world `points` [M, 3] seen from `frame` by
    its odometry: those in front of the camera and inside the image, in `points`' order."""
    if not len(points):
        return np.zeros((0, 3), np.float32)
    camera = geometry.transform_points(
        np.asarray(points, np.float64)[None],
        np.asarray(frame.rotation, np.float64),
        np.asarray(frame.translation, np.float64),
    )
    camera_matrix = geometry.intrinsics_matrix(
        np.asarray(frame.intrinsics, np.float64), height, width
    )
    pixels, depth = geometry.project(camera, camera_matrix)
    column, row, depth = np.round(pixels[0, :, 0]), np.round(pixels[0, :, 1]), depth[0]
    keep = (depth > 1e-6) & (row >= 0) & (row < height) & (column >= 0) & (column < width)
    return np.stack([row[keep], column[keep], depth[keep]], axis=1).astype(np.float32)
