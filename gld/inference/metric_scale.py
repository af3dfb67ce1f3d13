"""Metric scale from one measurement, with numpy alone: odometry's baseline or range readings.

A gld model is trained with the pair's translation scaled to ||t|| = 1, so it predicts
depth in units of the baseline between the two views. `scale_from_baseline` takes the
baseline in metres (metric depth = depth * baseline); `scale_from_ranges` the readings
(u, v, distance) of a range sensor (the median ratio of each reading to the predicted
depth there); `pair_scales` either, for a batch of pairs, as the predictors take them.

This module imports numpy alone: the runtime of an exported model
(`gld.inference.runtime`) uses it without OpenCV or the training stack.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from gld.inference.inputs import _readings

SCALE_SOURCES = ("baseline", "ranges", "none")


def scale_from_baseline(baseline: float | np.ndarray) -> np.ndarray:
    """Metres per model unit from the pair's baseline measured by odometry.

    The model is trained with ||t|| = 1, so metric depth = depth * baseline.

    Args:
      baseline: scalar or [B] distance in metres between the two camera centres.

    Returns:
      float32 array of the same shape as `baseline`: the scale(s), metres per unit.

    Raises:
      ValueError: naming the baseline that is not finite or not positive.
    """
    values = np.asarray(baseline, np.float64)
    if values.dtype.kind not in "fiu":
        raise ValueError(f"baseline must be a number in metres, got {baseline!r}")
    bad = ~(np.isfinite(values) & (values > 0))
    if np.any(bad):
        where = "" if values.ndim == 0 else f" at index {int(np.flatnonzero(bad)[0])}"
        first_bad = values[bad].flat[0] if values.ndim else float(values)
        raise ValueError(
            f"baseline must be finite and > 0 metres (a pair without translation has no "
            f"depth scale), got {first_bad}{where}"
        )
    return values.astype(np.float32)


def sample_bilinear(depth: np.ndarray, pixels: np.ndarray) -> np.ndarray:
    """Bilinear lookup of a map at sub-pixel positions.

    Args:
      depth: [H, W] map.
      pixels: [N, 2] (u, v) pixel-index coordinates ((0, 0) is the centre of the
        top-left pixel) within the image's extent [-0.5, W - 0.5] x [-0.5, H - 0.5];
        positions beyond the outer pixel centres take the edge value.

    Returns:
      [N] float64 values.
    """
    height, width = depth.shape
    u = np.clip(np.asarray(pixels[:, 0], np.float64), 0.0, width - 1)
    v = np.clip(np.asarray(pixels[:, 1], np.float64), 0.0, height - 1)
    left = np.minimum(np.floor(u).astype(np.int64), max(width - 2, 0))
    top = np.minimum(np.floor(v).astype(np.int64), max(height - 2, 0))
    right = np.minimum(left + 1, width - 1)
    bottom = np.minimum(top + 1, height - 1)
    du, dv = u - left, v - top
    values = np.asarray(depth, np.float64)
    upper = (1 - du) * values[top, left] + du * values[top, right]
    lower = (1 - du) * values[bottom, left] + du * values[bottom, right]
    return (1 - dv) * upper + dv * lower


def _check_readings(
    shape: tuple[int, int], pixels: np.ndarray, distances: np.ndarray, where: str
) -> None:
    """Raises ValueError naming the first reading outside the image or not a distance."""
    height, width = shape
    for index in range(len(distances)):
        u, v = pixels[index]
        distance = distances[index]
        reading = f"{where}reading {index} (u={u}, v={v}, distance={distance})"
        if not (np.isfinite(u) and np.isfinite(v) and np.isfinite(distance)):
            raise ValueError(f"{reading} is not finite")
        if not (-0.5 <= u <= width - 0.5 and -0.5 <= v <= height - 0.5):
            raise ValueError(f"{reading} lies outside the {width}x{height} image")
        if distance <= 0:
            raise ValueError(f"{reading}: distance must be > 0")


def _scale_one(depth: np.ndarray, pixels: np.ndarray, distances: np.ndarray, where: str) -> float:
    if depth.ndim != 2 or depth.size == 0:
        raise ValueError(f"{where}depth must be a non-empty [H, W] map, got shape {depth.shape}")
    if pixels.ndim != 2 or pixels.shape[-1] != 2 or len(pixels) == 0:
        raise ValueError(f"{where}pixels must be [N, 2] (u, v) with N >= 1, got {pixels.shape}")
    if distances.shape != (len(pixels),):
        raise ValueError(
            f"{where}distances must be [N] = [{len(pixels)}] like pixels, got {distances.shape}"
        )
    _check_readings(depth.shape, pixels, distances, where)
    predicted = sample_bilinear(depth, pixels)
    bad = ~(np.isfinite(predicted) & (predicted > 0))
    if np.any(bad):
        index = int(np.flatnonzero(bad)[0])
        u, v = pixels[index]
        raise ValueError(
            f"{where}reading {index} (u={u}, v={v}): the depth map there is "
            f"{predicted[index]}, not a positive depth"
        )
    return float(np.median(distances / predicted))


def scale_from_ranges(depth: np.ndarray, pixels: np.ndarray, distances: np.ndarray) -> np.ndarray:
    """The scale s such that s * depth matches range readings.

    s is the median over readings of distance / depth (robust to a few bad readings),
    the depth looked up bilinearly at each reading's pixel. Distances are camera-z
    depths, as in `data.demon.convert`'s range CSV (default `--depth_metric=camera_z`).

    Args:
      depth: [H, W] (or [B, H, W]) depth in model units.
      pixels: [N, 2] (u, v) in depth's pixel coordinates, (0, 0) the centre of the
        top-left pixel ([B, N, 2] batched).
      distances: [N] metres ([B, N] batched).

    Returns:
      float32 scale, metres per model unit: a scalar array, or [B].

    Raises:
      ValueError: naming the reading (index, pixel, distance) that lies outside the
        image, is not finite, is <= 0, or falls where depth is not positive; or the
        argument whose shape is wrong.
    """
    depth = np.asarray(depth)
    pixels = np.asarray(pixels, np.float64)
    distances = np.asarray(distances, np.float64)
    if depth.ndim == 2:
        return np.asarray(_scale_one(depth, pixels, distances, ""), np.float32)
    if depth.ndim != 3:
        raise ValueError(f"depth must be [H, W] or [B, H, W], got shape {depth.shape}")
    if pixels.ndim != 3 or len(pixels) != len(depth):
        raise ValueError(
            f"batched pixels must be [B, N, 2] with B = {len(depth)}, got {pixels.shape}"
        )
    if distances.ndim != 2 or len(distances) != len(depth):
        raise ValueError(
            f"batched distances must be [B, N] with B = {len(depth)}, got {distances.shape}"
        )
    return np.array(
        [
            _scale_one(depth[index], pixels[index], distances[index], f"example {index}: ")
            for index in range(len(depth))
        ],
        np.float32,
    )


def ray_length_to_depth(
    pixels: np.ndarray, distances: np.ndarray, camera_matrix: np.ndarray
) -> np.ndarray:
    """Distances along each pixel's ray (what a range sensor measures along its beam)
    -> camera-z depth: z = distance / ||K^-1 [u, v, 1]||.

    Args:
      pixels: [N, 2] (u, v) pixel-index coordinates.
      distances: [N] distances from the camera centre.
      camera_matrix: [3, 3] pixel-index K of the same pixels.

    Returns:
      [N] float64 camera-z depths.
    """
    pixels = np.asarray(pixels, np.float64).reshape(-1, 2)
    homogeneous = np.concatenate([pixels, np.ones((len(pixels), 1))], axis=-1)
    rays = homogeneous @ np.linalg.inv(np.asarray(camera_matrix, np.float64)).T
    return np.asarray(distances, np.float64) / np.linalg.norm(rays, axis=-1)


def pair_scales(
    depth: np.ndarray, baseline: Any, ranges: Any, single: bool
) -> tuple[np.ndarray, str]:
    """Metres per model unit for each pair of a batch, and the scale's source.

    Args:
      depth: [B, H, W] depth in baselines at the readings' pixels' resolution.
      baseline: None, one number or [B] metres (odometry).
      ranges: None, or the readings (u, v, distance): one [N, 3] array for one pair
        (`single`), a sequence of B such arrays for a batch.
      single: whether the caller gave one pair (its batch axis added).

    Returns:
      ([B] float32 scales, "baseline", "ranges" or "none"); ones without a measurement.
    """
    batch_size = len(depth)
    if baseline is not None and ranges is not None:
        raise ValueError("give baseline= or ranges=, not both")
    if baseline is not None:
        scales = scale_from_baseline(baseline)
        if scales.ndim == 0:
            scales = np.full(batch_size, scales, np.float32)
        if scales.shape != (batch_size,):
            raise ValueError(
                f"baseline must be one number or one per pair ([{batch_size}]), got "
                f"shape {np.shape(baseline)}"
            )
        return scales, "baseline"
    if ranges is None:
        return np.ones(batch_size, np.float32), "none"
    per_pair = [ranges] if single else list(ranges)
    if len(per_pair) != batch_size:
        raise ValueError(
            f"ranges must hold one [N, 3] array of readings per pair ({batch_size}), "
            f"got {len(per_pair)}"
        )
    scales = []
    for index, (pair_depth, pair_ranges) in enumerate(zip(depth, per_pair, strict=True)):
        where = "" if single else f"[{index}]"
        readings = _readings(pair_ranges, where)
        try:
            scales.append(scale_from_ranges(pair_depth, readings[:, :2], readings[:, 2]))
        except ValueError as error:
            raise ValueError(f"ranges{where}: {error}") from None
    return np.asarray(scales, np.float32), "ranges"
