"""How well a model's depth becomes metres: scale recovery measured on a dataset.

A robot recovers metres from either of two measurements (`gld.inference.metric_scale`):
odometry's baseline (`scale_from_baseline`) or range readings (`scale_from_ranges`).
`measure_scale_recovery` measures how well each recovers metric depth on a dataset's
test pairs, whose records hold the true metric depth and pose; `scale_table` prints it.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from gld import contract
from gld.inference.metric_scale import scale_from_baseline, scale_from_ranges

# The reading's pixel has its own random stream, apart from the input pipeline's
# augmentation (0) and supervised pixels (1).
_READING_STREAM = 2


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
