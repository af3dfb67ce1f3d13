"""Depth metrics of the paper (Abs-Inv, Abs-Rel, S-RMSE), pose errors, the protocol stamp
and tables.

Metrics are computed per example over the pixels DeMoN's metrics score (valid ground
truth, finite and positive prediction; the others are excluded and counted) and then
averaged over examples. The metric functions are jittable; per-example values come with
an example mask so that padded, sharded batches give exact means through (sum, count).
"""

from __future__ import annotations

import collections
import math
from collections.abc import Iterable, Mapping
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from gld import geometry

DEPTH_METRICS = ("abs_inv", "abs_rel", "s_rmse")
METRIC_NAMES = {"abs_inv": "Abs-Inv", "abs_rel": "Abs-Rel", "s_rmse": "S-RMSE"}
# Where the ground truth is scored (`protocol_stamp`): the records' resolution, or the
# source files' (DeMoN's, `gld.evaluation.evaluate.Truth`).
TRUTH_RESOLUTIONS = ("record", "file")


def depth_metrics(
    depth_pred: jax.Array, depth_true: jax.Array, valid: jax.Array
) -> dict[str, jax.Array]:
    """Per-example depth errors over the scored pixels (no median scaling).

    A pixel is scored where the ground truth is valid (`valid`, finite, > 0) and the
    prediction is finite and positive, as DeMoN's `compute_valid_depth_mask` decides;
    a valid ground-truth pixel with any other prediction is excluded and counted.
    Abs-Inv = mean |1/d - 1/d_hat|; Abs-Rel = mean |d - d_hat| / d;
    S-RMSE = sqrt(mean(E^2) - mean(E)^2) with E = log d - log d_hat (scale invariant).

    Args:
      depth_pred: [B, H, W] predicted depth.
      depth_true: [B, H, W] ground-truth depth.
      valid: [B, H, W] bool, pixels with valid ground truth.

    Returns:
      {"abs_inv", "abs_rel", "s_rmse", "num_pixels", "excluded_pixels"}, each [B]:
      num_pixels the scored pixels, excluded_pixels the valid ground-truth pixels left
      out for their prediction. An example without a scored pixel gets NaN errors
      (`summarise` leaves them out of the means and says so in its counts).
    """
    valid, scored, safe_true, safe_pred = scored_pixels(depth_pred, depth_true, valid)
    weight = scored.astype(jnp.float32)
    count = jnp.sum(weight, axis=(1, 2))
    denominator = jnp.maximum(count, 1.0)

    def mean(values):
        return jnp.sum(values * weight, axis=(1, 2)) / denominator

    log_error = jnp.log(safe_true) - jnp.log(safe_pred)
    variance = mean(log_error**2) - mean(log_error) ** 2
    errors = {
        "abs_inv": mean(jnp.abs(1.0 / safe_true - 1.0 / safe_pred)),
        "abs_rel": mean(jnp.abs(safe_true - safe_pred) / safe_true),
        "s_rmse": jnp.sqrt(jnp.maximum(variance, 0.0)),
    }
    per_example = {name: jnp.where(count > 0, value, jnp.nan) for name, value in errors.items()}
    per_example["num_pixels"] = count
    per_example["excluded_pixels"] = jnp.sum(valid & ~scored, axis=(1, 2)).astype(jnp.float32)
    return per_example


def scored_pixels(
    depth_pred: jax.Array, depth_true: jax.Array, valid: jax.Array
) -> tuple[jax.Array, jax.Array, jax.Array, jax.Array]:
    """Which pixels a depth error is scored on, and the depths to score them with.

    Returns:
      (valid: `valid` where the truth is finite and > 0; scored: those of them whose
      prediction is finite and > 0 (the others are excluded, and counted); safe_true,
      safe_pred: the depths where scored and 1 elsewhere, the prediction floored at 1e-12
      so that 1/d stays finite in float32).
    """
    valid = valid & (depth_true > 0) & jnp.isfinite(depth_true)
    scored = valid & jnp.isfinite(depth_pred) & (depth_pred > 0)
    safe_true = jnp.where(scored, depth_true, 1.0)
    safe_pred = jnp.where(scored, jnp.maximum(depth_pred, 1e-12), 1.0)
    return valid, scored, safe_true, safe_pred


def resize_nearest(depth: jax.Array, height: int, width: int) -> jax.Array:
    """[..., h, w] -> [..., height, width] by centre-aligned nearest neighbour: each output
    pixel takes the input pixel under its centre (DeMoN's evaluation resizes a
    prediction so, with scikit-image's order-0 resize; OpenCV's INTER_NEAREST_EXACT
    is the same rule). Jittable; numpy in gives numpy out."""

    def indices(source: int, target: int) -> np.ndarray:
        # floor((i + 1/2) * source / target) in integers, so centres on a pixel border
        # always go to the later pixel.
        return ((2 * np.arange(target) + 1) * source) // (2 * target)

    source_height, source_width = depth.shape[-2:]
    rows, cols = indices(source_height, height), indices(source_width, width)
    return depth[..., rows[:, None], cols[None, :]]


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
      name -> {"mean", "std", "count"} computed from sums, so padding never counts. A
      non-finite value (the errors of an example without a scored pixel) is left out:
      `count` says how many examples a mean is over.
    """
    mask = np.asarray(example_mask, bool)
    summary = {}
    for name, values in per_example.items():
        values = np.asarray(values, np.float64)[mask]
        values = values[np.isfinite(values)]
        count = int(values.size)
        if count == 0:
            summary[name] = {"mean": math.nan, "std": math.nan, "count": 0}
            continue
        mean = float(values.sum() / count)
        variance = float(np.maximum((values**2).sum() / count - mean**2, 0.0))
        summary[name] = {"mean": mean, "std": math.sqrt(variance), "count": count}
    return summary


def protocol_stamp(
    height: int,
    width: int,
    num_examples: int,
    extra: str = "",
    *,
    truth_resolution: str = "record",
    file_resolutions: Mapping[str, int] | None = None,
    records_protocol: Mapping[str, Any] | None = None,
) -> str:
    """One line saying exactly how a table's numbers were computed.

    Args:
      height, width: the records' resolution.
      num_examples: the examples the means are over.
      extra: appended after a "; ".
      truth_resolution: a `TRUTH_RESOLUTIONS` name: "record", the records' ground truth
        (a dataset builder resized that of files of another size, e.g. DeMoN's 640x480
        SUN3D and RGB-D files, when it wrote the records); "file", the ground truth of
        the source files, each prediction resized to it by `resize_nearest`, as DeMoN's
        evaluation does.
      file_resolutions: with "file", "<W>x<H>" -> how many examples had truth of that size.
      records_protocol: the records' build options (`records_protocol_note`), named last.
    """
    if truth_resolution not in TRUTH_RESOLUTIONS:
        raise ValueError(
            f"unknown truth_resolution {truth_resolution!r}; valid: {TRUTH_RESOLUTIONS}"
        )
    if truth_resolution == "file":
        sizes = ", ".join(f"{count} at {size}" for size, count in (file_resolutions or {}).items())
        where = (
            f"ground truth at the source files' resolution ({sizes or 'none'}), read from "
            f"the files by example id, each prediction resized to it by centre-aligned "
            f"nearest neighbour as DeMoN's evaluation does (records at {width}x{height} px)"
        )
    else:
        where = (
            f"ground truth at the records' resolution, {width}x{height} px (source files "
            f"of another size were resized when the records were built; DeMoN evaluates "
            f"at the file's, truth_resolution=file)"
        )
    stamp = (
        f"protocol: {where}; depth scaled so that ||t|| = 1; every valid ground-truth "
        f"pixel of each example whose prediction is finite and positive (others excluded "
        f"and counted, as in DeMoN's metrics); per-example means averaged over "
        f"{num_examples} examples; no median scaling"
    )
    records_note = records_protocol_note(records_protocol) if records_protocol else ""
    return "; ".join(filter(None, [stamp, extra, records_note]))


def resolution_counts(shapes: Iterable[tuple[int, int]]) -> dict[str, int]:
    """How many of the (height, width) `shapes` have each size, as {"<W>x<H>": count},
    the most frequent first: the `file_resolutions` of `protocol_stamp`."""
    return dict(collections.Counter(f"{width}x{height}" for height, width in shapes).most_common())


# What a records' `order` stamp means (`records_protocol_note`).
RECORD_ORDERS = {
    "demon": "DeMoN's reader's: files as listed, each file's scene groups reverse-sorted",
}


def records_protocol_note(protocol: Mapping[str, Any]) -> str:
    """One clause naming the protocol a split's records were built with, for the stamp.

    Args:
      protocol: build options of the split, e.g. {"image_decoder": "demon",
        "depth_resampling": "demon", "order": "demon"} (a DeMoN dataset's).
    """
    built = ", ".join(f"{key}={value}" for key, value in protocol.items() if key != "order")
    order = protocol.get("order")
    evaluated = "evaluated in the records' stored order"
    if order is not None:
        evaluated += f", order={order}" + (
            f" ({RECORD_ORDERS[order]})" if order in RECORD_ORDERS else ""
        )
    return f"records built with {built}; {evaluated}" if built else evaluated


def excluded_pixels(summary: Mapping[str, dict]) -> dict[str, Any] | None:
    """What a method's predictions left unscored, from its `summarise` summary.

    Returns:
      {"pixels": valid ground-truth pixels excluded, "valid_pixels": all valid
      ground-truth pixels, "fraction", "per_example": mean over examples,
      "unscored_examples": examples without a scored pixel (out of the error means)};
      None when the summary has no pixel counts.
    """
    if "excluded_pixels" not in summary or "num_pixels" not in summary:
        return None

    def total(entry: dict) -> int:
        return round(entry["mean"] * entry["count"]) if entry["count"] else 0

    excluded = summary["excluded_pixels"]
    pixels = total(excluded)
    valid_pixels = pixels + total(summary["num_pixels"])
    scored_examples = min(
        (summary[name]["count"] for name in DEPTH_METRICS if name in summary),
        default=excluded["count"],
    )
    return {
        "pixels": pixels,
        "valid_pixels": valid_pixels,
        "fraction": pixels / valid_pixels if valid_pixels else 0.0,
        "per_example": excluded["mean"] if excluded["count"] else 0.0,
        "unscored_examples": excluded["count"] - scored_examples,
    }


def exclusion_note(rows: Iterable[tuple[str, dict[str, dict]]]) -> str:
    """One line saying how many pixels each method had excluded ("" without pixel counts)."""
    parts, any_counts = [], False
    for method, summary in rows:
        excluded = excluded_pixels(summary)
        if excluded is None:
            continue
        any_counts = True
        if excluded["pixels"] == 0:
            continue
        part = (
            f"{method} {excluded['pixels']:,} of {excluded['valid_pixels']:,} "
            f"({excluded['fraction']:.2%})"
        )
        if excluded["unscored_examples"]:
            part += (
                f", {excluded['unscored_examples']} example(s) without a scored pixel "
                f"left out of its means"
            )
        parts.append(part)
    if not any_counts:
        return ""
    return (
        "Excluded pixels (valid ground truth, prediction not finite or not positive): "
        + ("; ".join(parts) if parts else "none")
        + "."
    )


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
    `ratios_to_reference`). When the summaries count pixels, a line under the table
    gives the excluded ones (`exclusion_note`).
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
    note = exclusion_note(rows)
    if note:
        lines += ["", note]
    return "\n".join(lines) + f"\n\n{stamp}\n"
