"""Metric scale: from the model's baseline units to metres.

A gld model is trained with the pair's translation scaled to ||t|| = 1, so it predicts
depth in units of the baseline between the two views. A robot recovers metres from
either of two measurements:

* odometry: the baseline in metres, `scale_from_baseline` (metric depth = depth * baseline);
* a range sensor: one or more readings (u, v, distance) in the image,
  `scale_from_ranges` (the median ratio of each reading to the predicted depth there).

    scale = scale_from_ranges(depth, pixels=[[64.0, 48.0]], distances=[2.31])
    metric_depth = scale * depth

`measure_scale_recovery` measures how well each recovers metric depth on a dataset's
test pairs, whose records hold the true metric depth and pose.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from gld import contract

SCALE_SOURCES = ("baseline", "ranges", "none")
# The reading's pixel has its own random stream, apart from the input pipeline's
# augmentation (0) and supervised pixels (1).
_READING_STREAM = 2


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


# ----------------------------------------------------------------- measurement


def abs_rel(depth: np.ndarray, depth_true: np.ndarray) -> float:
    """Mean |depth - truth| / truth over the pixels where the truth is finite and > 0."""
    valid = np.isfinite(depth_true) & (depth_true > 0)
    return float(np.mean(np.abs(depth[valid] - depth_true[valid]) / depth_true[valid]))


def best_abs_rel_scale(depth: np.ndarray, depth_true: np.ndarray) -> float:
    """The scale s minimising Abs-Rel(s * depth, truth) over the truth's valid pixels.

    mean |s d - t| / t = mean (d / t) |s - t / d|: the median of the ratios t / d
    weighted by d / t.
    """
    valid = np.isfinite(depth_true) & (depth_true > 0) & np.isfinite(depth) & (depth > 0)
    ratios = depth_true[valid] / depth[valid]
    weights = 1.0 / ratios
    order = np.argsort(ratios)
    cumulative = np.cumsum(weights[order])
    return float(ratios[order][np.searchsorted(cumulative, 0.5 * cumulative[-1])])


SCALE_METHODS = {
    "true_baseline": "true baseline (odometry without error)",
    "one_reading": "one range reading at a random valid pixel",
    "train_mean_baseline": "training-set mean baseline (no measurement)",
    "oracle_best_scale": "per-pair best single scale (sees the truth; reference)",
}


def measure_scale_recovery(
    predict_depth: Callable[[np.ndarray, np.ndarray, np.ndarray], np.ndarray],
    test_source: Sequence[Any],
    train_source: Sequence[Any] | None = None,
    *,
    train_mean_baseline: float | None = None,
    seed: int = 0,
    batch_size: int = 16,
    max_examples: int = 0,
    progress: Callable[[int], None] | None = None,
) -> dict[str, Any]:
    """Abs-Rel of metric depth against the true metric depth, for each way of scaling.

    For every test pair, depth in baseline units is predicted once and scaled to metres
    by: the true baseline ||t|| (what perfect odometry gives); one range reading at a
    valid pixel drawn at random (seeded by `seed` and the example id), its distance the
    true depth there; the training set's mean baseline (no measurement at all); and, as
    a reference, each pair's best single scale (`best_abs_rel_scale`, which sees the
    truth): the error left is the map's shape, which no scale can fix.

    Args:
      predict_depth: (images1 [B, H, W, 3] float in [0, 1], images2, flow [B, H, W, 2])
        -> depth [B, H, W] in baseline units, e.g. a `gld.inference.predict.DepthPredictor`.
      test_source, train_source: data sources of stored records (`gld.records`).
      train_mean_baseline: the mean ||t|| to use instead of reading `train_source`.
      seed: seeds the reading's pixel.
      batch_size: pairs per prediction call.
      max_examples: the first N test pairs only (0 = all).
      progress: called with the number of pairs done after each batch.

    Returns:
      {"methods": {name: {"abs_rel": mean, "abs_rel_std": std, "description": ...}},
       "num_examples": int, "train_mean_baseline": float, "per_example": {name: [..]}}.
    """

    if train_mean_baseline is None:
        if train_source is None or len(train_source) == 0:
            raise ValueError("the training-set mean baseline needs a non-empty train_source")
        baselines = [
            float(np.linalg.norm(np.asarray(train_source[i]["translation"], np.float64)))
            for i in range(len(train_source))
        ]
        train_mean_baseline = float(np.mean(baselines))
    count = len(test_source) if max_examples <= 0 else min(max_examples, len(test_source))
    if count == 0:
        raise ValueError("no test examples to measure scale recovery on")
    per_example: dict[str, list[float]] = {name: [] for name in SCALE_METHODS}
    for start in range(0, count, batch_size):
        examples = [
            contract.decode_example(test_source[i], where=f"test record {i}")
            for i in range(start, min(start + batch_size, count))
        ]
        depth_units = predict_depth(
            np.stack([example["image1"] + 0.5 for example in examples]),
            np.stack([example["image2"] + 0.5 for example in examples]),
            np.stack([example["flow"] for example in examples]),
        )
        for example, predicted in zip(examples, np.asarray(depth_units), strict=True):
            truth = example["depth"]
            valid_pixels = np.argwhere(example["depth_valid"])
            if len(valid_pixels) == 0:
                continue
            rng = contract.example_rng(seed, str(example["id"]), 0, _READING_STREAM)
            row, column = valid_pixels[rng.integers(len(valid_pixels))]
            scales = {
                "true_baseline": scale_from_baseline(np.linalg.norm(example["translation"])),
                "one_reading": scale_from_ranges(
                    predicted, [[float(column), float(row)]], [float(truth[row, column])]
                ),
                "train_mean_baseline": scale_from_baseline(train_mean_baseline),
                "oracle_best_scale": best_abs_rel_scale(predicted, truth),
            }
            for name, scale in scales.items():
                per_example[name].append(abs_rel(float(scale) * predicted, truth))
        if progress is not None:
            progress(min(start + batch_size, count))
    methods = {
        name: {
            "abs_rel": float(np.mean(values)),
            "abs_rel_std": float(np.std(values)),
            "description": SCALE_METHODS[name],
        }
        for name, values in per_example.items()
    }
    return {
        "methods": methods,
        "num_examples": len(per_example["true_baseline"]),
        "train_mean_baseline": train_mean_baseline,
        "per_example": per_example,
    }


def scale_table(result: dict[str, Any]) -> str:
    """A markdown table of `measure_scale_recovery`'s result."""
    lines = [
        f"Metric depth from baseline units, {result['num_examples']} test pairs "
        f"(training-set mean baseline {result['train_mean_baseline']:.4g} m):",
        "",
        "| scale from | Abs-Rel (metric) |",
        "|---|---|",
    ]
    for entry in result["methods"].values():
        lines.append(
            f"| {entry['description']} | {entry['abs_rel']:.3f} ± {entry['abs_rel_std']:.3f} |"
        )
    return "\n".join(lines)
