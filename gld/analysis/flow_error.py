"""Robustness to flow errors: per-pixel Abs-Inv depth error binned by optical-flow error.

The paper's "Robustness to Optical Flow Outliers" figure plots, for each method, the
mean (± std) per-pixel Abs-Inv error |1/d - 1/d_hat| (depth in the contract's scale,
||t|| = 1) over the pixels whose input flow has a given end-point error, normalised by
the image size. Here:

    curves = flow_error_curves(
        {"global_local": model_predictor(model, variables),
         "triangulation_gt_pose": triangulation_predictor()},
        source, batch_size=16)
    draw_flow_error_curves(curves, "flow_errors.png")

A predictor is a `DepthMethod`: a function of an example-contract batch returning
depth [B, H, W], with the contract keys it reads, so the pipeline decodes only those.
Statistics are accumulated per bin as (sum, sum of squares, count) in a `FlowErrorBins`,
so batches (and processes) add up exactly and the mean and std are taken once.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from gld import contract, input_pipeline
from gld.evaluation import metrics, reports
from gld.models import layers
from gld.models.baselines import classical

Batch = Mapping[str, Any]
Array = Any  # np.ndarray | jax.Array

# What the analysis itself reads: the input flow against the true flow, and the truth.
ANALYSIS_KEYS = ("flow", "gt_flow", "gt_flow_valid", "depth", "depth_valid")
# What triangulating a batch's flow needs besides the pose.
TRIANGULATION_KEYS = ("flow", "intrinsics1", "intrinsics2")
# The batch's true relative pose.
POSE_KEYS = ("rotation", "translation")
# Default bins: 4 per decade of normalised flow error from 1e-4 (0.03 px at 256 px,
# below any estimator's precision) to 1 (an error as large as the image), with an
# underflow bin [0, 1e-4) and an overflow bin [1, inf) so that every pixel is counted.
DEFAULT_LOWEST_ERROR = 1e-4
DEFAULT_HIGHEST_ERROR = 1.0
DEFAULT_BINS_PER_DECADE = 4


# ------------------------------------------------------------------ per-pixel errors


def normalised_flow_error(flow: Array, gt_flow: Array) -> jax.Array:
    """End-point error of a flow, with u in fractions of the width and v of the height.

    Args:
      flow: [..., H, W, 2] pixels, I1 -> I2 (the estimate).
      gt_flow: [..., H, W, 2] pixels, the true flow.

    Returns:
      [..., H, W] `sqrt((du / W)^2 + (dv / H)^2)`, the normalisation of
      `gld.models.layers.normalise_flow`.
    """
    flow, gt_flow = jnp.asarray(flow, jnp.float32), jnp.asarray(gt_flow, jnp.float32)
    if flow.shape != gt_flow.shape or flow.ndim < 3 or flow.shape[-1] != 2:
        raise ValueError(
            f"flow and gt_flow must both be [..., H, W, 2], got {flow.shape} and {gt_flow.shape}"
        )
    return jnp.linalg.norm(layers.normalise_flow(flow - gt_flow), axis=-1)


def per_pixel_abs_inv(
    depth_pred: Array, depth_true: Array, valid: Array
) -> tuple[jax.Array, jax.Array]:
    """Per-pixel Abs-Inv error |1/d - 1/d_hat| over the pixels `gld.evaluation.metrics` scores.

    A pixel is usable where the truth is valid (`valid`, finite, > 0) and the prediction
    finite and > 0, as in `gld.evaluation.metrics.depth_metrics`; a valid ground-truth pixel with
    any other prediction is excluded (`valid & ~usable` counts them).

    Args:
      depth_pred: [..., H, W] predicted depth.
      depth_true: [..., H, W] true depth (contract scale, ||t|| = 1).
      valid: [..., H, W] bool, the pixels to consider.

    Returns:
      error [..., H, W] float32 (NaN where not usable) and usable [..., H, W] bool.
    """
    depth_pred = jnp.asarray(depth_pred, jnp.float32)
    depth_true = jnp.asarray(depth_true, jnp.float32)
    if depth_pred.shape != depth_true.shape:
        raise ValueError(
            f"depth_pred {depth_pred.shape} and depth_true {depth_true.shape} must match"
        )
    _, usable, safe_true, safe_pred = metrics.scored_pixels(
        depth_pred, depth_true, jnp.asarray(valid, bool)
    )
    error = jnp.abs(1.0 / safe_true - 1.0 / safe_pred)
    return jnp.where(usable, error, jnp.nan), usable


# ----------------------------------------------------------------------------- bins


def log_edges(
    lowest: float = DEFAULT_LOWEST_ERROR,
    highest: float = DEFAULT_HIGHEST_ERROR,
    bins_per_decade: int = DEFAULT_BINS_PER_DECADE,
) -> np.ndarray:
    """Bin edges [K + 1] of normalised flow error: 0, then log-spaced from `lowest` to
    `highest` with `bins_per_decade` bins per decade (rounded to whole bins), then inf.

    The first bin [0, lowest) holds the (near-)exact flow, the last [highest, inf) the
    errors beyond the image size.
    """
    if not 0 < lowest < highest or bins_per_decade < 1:
        raise ValueError(
            f"need 0 < lowest < highest and bins_per_decade >= 1, got lowest={lowest}, "
            f"highest={highest}, bins_per_decade={bins_per_decade}"
        )
    decades = math.log10(highest / lowest)
    inner = np.geomspace(lowest, highest, max(1, round(decades * bins_per_decade)) + 1)
    return np.concatenate([[0.0], inner, [np.inf]])


def _check_edges(edges: Array) -> np.ndarray:
    edges = np.asarray(edges, np.float64)
    if (
        edges.ndim != 1
        or edges.size < 2
        or edges[0] != 0
        or edges[-1] != np.inf
        or np.any(np.diff(edges) <= 0)
    ):
        raise ValueError(
            "edges must be strictly increasing from 0 to inf (so that every flow error "
            f"falls in a bin), e.g. log_edges(); got {edges.tolist()}"
        )
    return edges


@dataclasses.dataclass(frozen=True, eq=False)
class FlowErrorBins:
    """Per-bin sums of a per-pixel error, binned by normalised flow error.

    Bin k holds the pixels with edges[k] <= flow error < edges[k + 1]. Bins of the same
    edges add (`add`, `+`), so batches and processes accumulate exactly.

    Attributes:
      edges: [K + 1] float64, 0 first and inf last.
      sum, sum_squares: [K] float64 sums of the error and of its square.
      count: [K] int64 pixels.
    """

    edges: np.ndarray
    sum: np.ndarray
    sum_squares: np.ndarray
    count: np.ndarray

    @classmethod
    def zeros(cls, edges: Array | None = None) -> FlowErrorBins:
        """Empty bins of `edges` (default `log_edges()`)."""
        edges = _check_edges(log_edges() if edges is None else edges)
        num_bins = edges.size - 1
        return cls(edges, np.zeros(num_bins), np.zeros(num_bins), np.zeros(num_bins, np.int64))

    def add(self, other: FlowErrorBins) -> FlowErrorBins:
        """The bins of both (same edges)."""
        if not np.array_equal(self.edges, other.edges):
            raise ValueError(
                f"cannot add bins of different edges: {self.edges.tolist()} and "
                f"{other.edges.tolist()}"
            )
        return FlowErrorBins(
            self.edges,
            self.sum + other.sum,
            self.sum_squares + other.sum_squares,
            self.count + other.count,
        )

    __add__ = add


def bin_statistics(
    flow_error: Array, depth_error: Array, mask: Array, edges: Array | None = None
) -> FlowErrorBins:
    """Bins the masked pixels' `depth_error` by their `flow_error`.

    Args:
      flow_error: [...] normalised flow error (>= 0 where `mask`).
      depth_error: [...] per-pixel error of the same shape (finite where `mask`).
      mask: [...] bool, the pixels to count.
      edges: [K + 1] from 0 to inf (default `log_edges()`).

    Returns:
      the pixels' `FlowErrorBins`.
    """
    edges = _check_edges(log_edges() if edges is None else edges)
    flow_error = np.asarray(flow_error, np.float64)
    depth_error = np.asarray(depth_error, np.float64)
    mask = np.asarray(mask, bool)
    if not flow_error.shape == depth_error.shape == mask.shape:
        raise ValueError(
            f"flow_error {flow_error.shape}, depth_error {depth_error.shape} and mask "
            f"{mask.shape} must have one shape"
        )
    flow_error, depth_error = flow_error[mask], depth_error[mask]
    if not (np.all(np.isfinite(depth_error)) and np.all(flow_error >= 0)):
        raise ValueError("masked pixels need finite depth errors and flow errors >= 0")
    num_bins = edges.size - 1
    # side="right": a pixel exactly on an edge goes to the bin that edge opens.
    index = np.searchsorted(edges, flow_error, side="right") - 1
    return FlowErrorBins(
        edges,
        np.bincount(index, depth_error, num_bins),
        np.bincount(index, depth_error**2, num_bins),
        np.bincount(index, minlength=num_bins).astype(np.int64),
    )


def bin_centres(edges: Array) -> np.ndarray:
    """[K] positions of the bins on a log axis: the geometric mean of a bin's edges; the
    first bin [0, e1) and the last [e_{K-1}, inf) sit half a neighbour's log-width
    beyond their finite edge."""
    edges = _check_edges(edges)
    finite = edges[1:-1]
    if finite.size < 2:
        # One finite edge gives no log-width: the bins sit a factor 2 either side of it.
        return np.concatenate([finite / 2, finite * 2]) if finite.size else np.ones(1)
    inner = np.sqrt(finite[:-1] * finite[1:])
    first = finite[0] * math.sqrt(finite[0] / finite[1])
    last = finite[-1] * math.sqrt(finite[-1] / finite[-2])
    return np.concatenate([[first], inner, [last]])


def summarise(bins: FlowErrorBins) -> dict[str, np.ndarray]:
    """Mean and population std of each bin.

    Returns:
      {"edges": [K + 1], "centres": [K] (`bin_centres`), "mean": [K], "std": [K],
       "count": [K] int64}; an empty bin has NaN mean and std and count 0.
    """
    count = bins.count
    safe_count = np.maximum(count, 1)
    mean = bins.sum / safe_count
    variance = np.maximum(bins.sum_squares / safe_count - mean**2, 0.0)
    empty = count == 0
    return {
        "edges": bins.edges,
        "centres": bin_centres(bins.edges),
        "mean": np.where(empty, np.nan, mean),
        "std": np.where(empty, np.nan, np.sqrt(variance)),
        "count": count,
    }


# ----------------------------------------------------------------------- predictors


@dataclasses.dataclass(frozen=True)
class DepthMethod:
    """A depth method for `flow_error_curves`.

    Attributes:
      predict: example-contract batch (numpy, leading [B]) -> depth [B, H, W] in the
        contract's scale (||t|| = 1); non-finite or non-positive where it has none.
      keys: the contract keys `predict` reads (those beyond `ANALYSIS_KEYS` are decoded
        for it only).
    """

    predict: Callable[[Batch], Array]
    keys: tuple[str, ...] = ()

    def __call__(self, batch: Batch) -> Array:
        return self.predict(batch)


def triangulated_depth(batch: Batch, rotation: Array, translation: Array) -> Array:
    """Classic per-pixel triangulation of the batch's input flow with a given pose.

    `gld.models.baselines.classical.triangulate_batch`, the `triangulation_gt_pose` baseline's
    method: the translation is rescaled to norm 1 (the contract's scale, so a predicted
    unit direction is at the batch's scale), and a pixel that does not triangulate
    (no parallax, behind a camera, nearer than 0.01) gets its pair's median triangulated
    inverse depth, as in the tables.

    Args:
      batch: "flow" [B, H, W, 2] pixels I1 -> I2, "intrinsics1", "intrinsics2" [B, 4].
      rotation, translation: [B, 3, 3], [B, 3]; X2 = R X1 + t.

    Returns:
      depth [B, H, W], positive and finite (numpy for numpy inputs).
    """

    return classical.triangulate_batch(
        batch["flow"], batch["intrinsics1"], batch["intrinsics2"], rotation, translation
    )["depth"]


def triangulation_predictor(
    pose: Callable[[Batch], tuple[Array, Array]] | None = None,
    pose_keys: Sequence[str] = (),
) -> DepthMethod:
    """Triangulation of the input flow (`triangulated_depth`) with the batch's true pose,
    or with `pose(batch) -> (rotation [B, 3, 3], translation [B, 3])` reading `pose_keys`
    (e.g. the pose a network predicts)."""
    if pose is None:
        return DepthMethod(
            lambda batch: triangulated_depth(batch, batch["rotation"], batch["translation"]),
            TRIANGULATION_KEYS + POSE_KEYS,
        )
    return DepthMethod(
        lambda batch: triangulated_depth(batch, *pose(batch)),
        TRIANGULATION_KEYS + tuple(pose_keys),
    )


def model_predictor(model, variables: dict) -> DepthMethod:
    """A depth model's (e.g. the global-local model's) "depth" output, jitted; it reads
    `gld.models.layers.input_keys(model)`."""
    apply = jax.jit(
        lambda variables, batch: layers.apply_model(model, variables, batch, train=False)["depth"]
    )
    keys = layers.input_keys(model)
    return DepthMethod(
        lambda batch: apply(variables, {key: batch[key] for key in keys}), tuple(keys)
    )


# ------------------------------------------------------------------------- analysis


def flow_error_curves(
    predictors: Mapping[str, Callable[[Batch], Array]],
    source: Sequence[Any],
    *,
    batch_size: int,
    flow_source: str = "estimated",
    edges: Array | None = None,
    max_examples: int = 0,
) -> dict[str, dict[str, Any]]:
    """Per-pixel Abs-Inv of each predictor against the input flow's normalised error.

    One pass over `source` (this process's view; single process): the pixels counted are
    those of real rows (`example_mask`) with true flow (`gt_flow_valid`) and valid depth;
    each predictor's excluded pixels among them (prediction non-finite or <= 0) are
    counted apart.

    Args:
      predictors: name -> `DepthMethod` (or any callable batch -> depth [B, H, W]
        with a `keys` attribute; without one it may read `ANALYSIS_KEYS` only).
      source: random-access records (e.g. `builder.as_data_source("test")`).
      batch_size: examples per batch.
      flow_source: the input flow; must be "estimated" (the true flow has no error).
      edges: [K + 1] bin edges from 0 to inf (default `log_edges()`).
      max_examples: the first this many records (0 = all).

    Returns:
      name -> `summarise` of its bins ({"edges", "centres", "mean", "std", "count"}) plus
      "pixels" (int, the pixels counted) and "excluded_pixels" (int, left out for the
      prediction).
    """
    if flow_source == "gt":
        raise ValueError(
            'flow_source="gt" feeds the true flow, whose error is 0 everywhere: the curve '
            'needs the estimated flow (flow_source="estimated")'
        )
    if flow_source not in contract.FLOW_SOURCES:
        raise ValueError(f"unknown flow_source {flow_source!r}; valid: {contract.FLOW_SOURCES}")
    if not predictors:
        raise ValueError("no predictors")
    edges = _check_edges(log_edges() if edges is None else edges)
    keys = list(ANALYSIS_KEYS)
    for predictor in predictors.values():
        keys += [key for key in getattr(predictor, "keys", ()) if key not in keys]

    bins = {name: FlowErrorBins.zeros(edges) for name in predictors}
    excluded = dict.fromkeys(predictors, 0)
    batches = input_pipeline.eval_batches(
        input_pipeline.first_records(source, max_examples),
        batch_size=batch_size,
        flow_source=flow_source,
        keys=tuple(keys),
    )
    for batch in batches:
        counted = (
            np.asarray(batch["example_mask"], bool)[:, None, None]
            & np.asarray(batch["gt_flow_valid"], bool)
            & np.asarray(batch["depth_valid"], bool)
        )
        flow_error = np.asarray(normalised_flow_error(batch["flow"], batch["gt_flow"]))
        for name, predictor in predictors.items():
            depth_pred = predictor(batch)
            if tuple(np.shape(depth_pred)) != counted.shape:
                raise ValueError(
                    f"predictor {name!r} returned shape {np.shape(depth_pred)}, expected "
                    f"[B, H, W] = {counted.shape}"
                )
            error, usable = per_pixel_abs_inv(depth_pred, batch["depth"], counted)
            usable = np.asarray(usable)
            bins[name] = bins[name] + bin_statistics(flow_error, np.asarray(error), usable, edges)
            excluded[name] += int(counted.sum() - usable.sum())

    curves = {}
    for name, method_bins in bins.items():
        curves[name] = summarise(method_bins)
        curves[name]["pixels"] = int(method_bins.count.sum())
        curves[name]["excluded_pixels"] = excluded[name]
    return curves


def draw_flow_error_curves(
    curves: Mapping[str, Mapping[str, Any]], path: str | Path, *, title: str = ""
) -> Path:
    """Draws one line per method (mean per bin, ± std shaded) on log-log axes: the
    errors of triangulation span orders of magnitude, and a linear axis would flatten the
    other curves to zero. Where mean - std is not positive the band starts at mean / 10.

    Args:
      curves: name -> summary as from `flow_error_curves` (or `summarise`).
      path: the PNG to write (its directory is created).
      title: the figure's title.

    Returns:
      the PNG's path.
    """

    plt = reports.pyplot()

    figure, axis = plt.subplots(figsize=(6, 4))
    for name, curve in curves.items():
        filled = np.asarray(curve["count"]) > 0
        centres = np.asarray(curve["centres"])[filled]
        mean = np.asarray(curve["mean"])[filled]
        std = np.asarray(curve["std"])[filled]
        (line,) = axis.plot(centres, mean, marker="o", markersize=3, label=name)
        lower = np.where(mean - std > 0, mean - std, mean / 10)
        axis.fill_between(centres, lower, mean + std, color=line.get_color(), alpha=0.2)
    axis.set_xscale("log")
    axis.set_yscale("log")
    axis.set_xlabel("normalised flow error")
    axis.set_ylabel("per-pixel Abs-Inv")
    axis.grid(True, which="major", alpha=0.3)
    if curves:
        axis.legend()
    if title:
        axis.set_title(title)
    return reports.save_figure(figure, path)
