"""Depth metrics of the paper (Abs-Inv, Abs-Rel, S-RMSE) and pose errors.

Metrics are computed per example over its valid ground-truth pixels and then
averaged over examples. Every function is jittable; per-example values come with an
example mask so that padded, sharded batches give exact means through (sum, count).
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping

import jax
import jax.numpy as jnp
import numpy as np

from gld import geometry

DEPTH_METRICS = ("abs_inv", "abs_rel", "s_rmse")
METRIC_NAMES = {"abs_inv": "Abs-Inv", "abs_rel": "Abs-Rel", "s_rmse": "S-RMSE"}


def depth_metrics(
    depth_pred: jax.Array, depth_true: jax.Array, valid: jax.Array
) -> dict[str, jax.Array]:
    """Per-example depth errors over valid pixels (no median scaling).

    Abs-Inv = mean |1/d - 1/d_hat|; Abs-Rel = mean |d - d_hat| / d;
    S-RMSE = sqrt(mean(E^2) - mean(E)^2) with E = log d - log d_hat (scale invariant).

    Args:
      depth_pred: [B, H, W] predicted depth (positive).
      depth_true: [B, H, W] ground-truth depth.
      valid: [B, H, W] bool, pixels with valid ground truth.

    Returns:
      {"abs_inv", "abs_rel", "s_rmse", "num_pixels"}, each [B]. An example without valid
      pixels gets 0 everywhere and num_pixels 0 (exclude it with `example_mask`).
    """
    valid = valid & (depth_true > 0) & jnp.isfinite(depth_true)
    safe_true = jnp.where(valid, depth_true, 1.0)
    safe_pred = jnp.where(valid, jnp.maximum(depth_pred, 1e-12), 1.0)
    weight = valid.astype(jnp.float32)
    count = jnp.sum(weight, axis=(1, 2))
    denominator = jnp.maximum(count, 1.0)

    def mean(values):
        return jnp.sum(values * weight, axis=(1, 2)) / denominator

    log_error = jnp.log(safe_true) - jnp.log(safe_pred)
    variance = mean(log_error**2) - mean(log_error) ** 2
    return {
        "abs_inv": mean(jnp.abs(1.0 / safe_true - 1.0 / safe_pred)),
        "abs_rel": mean(jnp.abs(safe_true - safe_pred) / safe_true),
        "s_rmse": jnp.sqrt(jnp.maximum(variance, 0.0)),
        "num_pixels": count,
    }


def pose_errors(
    rotation: jax.Array,
    translation: jax.Array,
    rotation_true: jax.Array,
    translation_true: jax.Array,
) -> dict[str, jax.Array]:
    """Per-example rotation and translation-direction errors in degrees, each [B]."""
    return {
        "rotation_deg": geometry.rotation_error_degrees(rotation, rotation_true),
        "translation_deg": geometry.translation_error_degrees(translation, translation_true),
    }


def summarise(per_example: dict[str, np.ndarray], example_mask: np.ndarray) -> dict[str, dict]:
    """Mean and standard deviation over examples of every per-example metric.

    Args:
      per_example: name -> [N] values (N may include padding).
      example_mask: [N] bool, the real examples.

    Returns:
      name -> {"mean", "std", "count"} computed from sums, so padding never counts.
    """
    mask = np.asarray(example_mask, bool)
    count = int(mask.sum())
    summary = {}
    for name, values in per_example.items():
        values = np.asarray(values, np.float64)[mask]
        if count == 0:
            summary[name] = {"mean": math.nan, "std": math.nan, "count": 0}
            continue
        mean = float(values.sum() / count)
        variance = float(np.maximum((values**2).sum() / count - mean**2, 0.0))
        summary[name] = {"mean": mean, "std": math.sqrt(variance), "count": count}
    return summary


def protocol_stamp(height: int, width: int, num_examples: int, extra: str = "") -> str:
    """One line saying exactly how a table's numbers were computed."""
    stamp = (
        f"protocol: {width}x{height} px; depth scaled so that ||t|| = 1; all valid "
        f"ground-truth pixels of each example; per-example means averaged over "
        f"{num_examples} examples; no median scaling"
    )
    return f"{stamp}; {extra}" if extra else stamp


def ratios_to_reference(
    rows: Iterable[tuple[str, dict[str, dict]]],
    reference: str = "dataset_mean",
    metric: str = "abs_inv",
) -> dict[str, float]:
    """Each method's mean `metric` as a multiple of the reference method's.

    Args:
      rows: (method, summary) pairs, summaries as made by `summarise`.
      reference: the method every other is divided by.
      metric: the per-example metric compared.

    Returns:
      method -> mean / reference mean, for every method with `metric`; empty when the
      reference is missing or its mean is not a positive number.
    """
    rows = list(rows)
    means = {method: summary[metric]["mean"] for method, summary in rows if metric in summary}
    reference_mean = means.get(reference, math.nan)
    if not (math.isfinite(reference_mean) and reference_mean > 0):
        return {}
    return {method: mean / reference_mean for method, mean in means.items()}


def table_name(method: str, labels: Mapping[str, str] | None = None) -> str:
    """How a table names a method: "name — label" where `labels` has one, else the name."""
    return f"{method} — {labels[method]}" if labels and method in labels else method


def markdown_table(
    rows: Iterable[tuple[str, dict[str, dict]]],
    stamp: str,
    metrics=DEPTH_METRICS,
    *,
    labels: Mapping[str, str] | None = None,
    reference: str = "dataset_mean",
) -> str:
    """Rows of (method, summary) -> a Markdown table with mean ± std, and the stamp.

    Methods are named by `table_name`. When the `reference` method is among the rows, a
    last column gives each method's Abs-Inv as a multiple of the reference's (see
    `ratios_to_reference`).
    """
    rows = list(rows)
    ratios = ratios_to_reference(rows, reference)
    names = [METRIC_NAMES.get(m, m) for m in metrics]
    if ratios:
        names.append(f"{METRIC_NAMES['abs_inv']} ÷ {reference}")
    lines = ["| method | " + " | ".join(names) + " |", "|---" * (len(names) + 1) + "|"]
    for method, summary in rows:
        cells = [
            f"{summary[m]['mean']:.4f} ± {summary[m]['std']:.4f}" if m in summary else "—"
            for m in metrics
        ]
        if ratios:
            cells.append(f"{ratios[method]:.2f}×" if method in ratios else "—")
        lines.append(f"| {table_name(method, labels)} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + f"\n\n{stamp}\n"
