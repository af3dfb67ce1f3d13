"""Where a learned depth model beats the classical pipeline, pair by pair: the properties
of a pair that decide it, their bins, the summary table and the figure.

    pose = sfm_flow_pose(example)                          # the classical pipeline's pose
    properties = pair_properties(example, pose)            # one decoded pair, raw scale
    kind, share = dominant_texture(texture_kind, example["depth_valid"], names)
    labels, edges = quantile_bins(values, 3)               # per pair: its bin's label
    rows = summarise_bins(labels, model_abs_inv, reference_abs_inv)
    text = markdown_summary(tables, model="global_local", reference="sfm_flow")
    draw_regimes(path, properties, ratios, edges=...)

A pair's properties (`PROPERTIES`) are read from the example before scale normalisation
(`gld.contract.decode_example`): the baseline is the raw ||t||. The comparison is
of per-pair Abs-Inv (the evaluation's per-example CSVs); the model "wins" a pair when
its Abs-Inv is below the reference's.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from gld import flow as flow_lib
from gld import geometry
from gld.evaluation import reports
from gld.models.baselines import classical

# The continuous per-pair properties, with the words a table or an axis shows for each.
PROPERTIES = {
    "baseline": "baseline: raw translation norm",
    "rotation_share": "rotation share of the true flow",
    "flow_epe_px": "flow end-point error (px)",
    "sfm_rotation_error_deg": "sfm_flow rotation error (deg)",
    "sfm_translation_error_deg": "sfm_flow translation error (deg)",
}
# Errors spread over decades: the figure draws them on a log axis.
LOG_SCALE_PROPERTIES = ("flow_epe_px", "sfm_rotation_error_deg", "sfm_translation_error_deg")
# The categorical property: the texture kind covering most of a pair's scored pixels.
TEXTURE_PROPERTY = "texture_kind"


def sfm_flow_pose(
    example: Mapping[str, Any], pipeline: classical.SfMFlow | None = None
) -> tuple[np.ndarray, np.ndarray, bool]:
    """The pose the classical pipeline estimates from the pair's flow (its essential
    matrix, `classical.SfMFlow.estimate_pose`; default settings, as the evaluation's).

    Args:
      example: 'flow' [H, W, 2] pixels I1 -> I2; 'intrinsics1', 'intrinsics2' [4]
        normalised.
      pipeline: the pipeline whose estimator is used (None: default settings).

    Returns:
      rotation [3, 3], unit translation [3] (X2 = R X1 + t), whether it succeeded.
    """
    pipeline = pipeline or classical.SfMFlow()
    flow = np.asarray(example["flow"], np.float64)
    height, width = flow.shape[:2]
    return pipeline.estimate_pose(
        flow,
        geometry.intrinsics_matrix(np.asarray(example["intrinsics1"], np.float64), height, width),
        geometry.intrinsics_matrix(np.asarray(example["intrinsics2"], np.float64), height, width),
    )


def rotation_share(example: Mapping[str, Any]) -> float:
    """How much of the pair's true flow its rotation makes: mean |rotation-only flow| over
    mean |true flow|, both over the valid true-flow pixels.

    The rotation-only flow is the pair's flow with the translation set to zero (the flow
    at infinite depth, which carries no depth). A pure rotation gives 1, a pure
    translation 0; the share can exceed 1 where the translation's flow cancels part of
    the rotation's.

    Args:
      example: 'gt_flow' [H, W, 2] pixels; 'gt_flow_valid' [H, W] bool; 'intrinsics1',
        'intrinsics2' [4] normalised; 'rotation' [3, 3].

    Returns:
      The share; NaN without a valid pixel or without motion.
    """
    gt_flow = np.asarray(example["gt_flow"], np.float64)
    valid = np.asarray(example["gt_flow_valid"], bool)
    height, width = valid.shape
    rotational_flow, _ = geometry.depth_to_flow(
        np.ones((height, width)),
        geometry.intrinsics_matrix(np.asarray(example["intrinsics1"], np.float64), height, width),
        geometry.intrinsics_matrix(np.asarray(example["intrinsics2"], np.float64), height, width),
        np.asarray(example["rotation"], np.float64),
        np.zeros(3),
    )
    flow_magnitude = np.linalg.norm(gt_flow, axis=-1)[valid]
    if not valid.any() or flow_magnitude.mean() <= 0:
        return float("nan")
    return float(np.linalg.norm(rotational_flow, axis=-1)[valid].mean() / flow_magnitude.mean())


def pair_properties(
    example: Mapping[str, Any], estimated_pose: tuple[np.ndarray, np.ndarray, bool]
) -> dict[str, float]:
    """The `PROPERTIES` of one pair, and whether the classical pose failed.

    Args:
      example: a decoded example before scale normalisation (`decode_example`): 'flow',
        'gt_flow' [H, W, 2] pixels; 'gt_flow_valid' [H, W] bool; 'intrinsics1',
        'intrinsics2' [4]; 'rotation' [3, 3]; 'translation' [3], raw.
      estimated_pose: (rotation [3, 3], translation [3], succeeded), e.g. `sfm_flow_pose`.

    Returns:
      baseline: ||t||; rotation_share (`rotation_share`); flow_epe_px: the estimated
      flow's end-point error over the valid true-flow pixels; sfm_rotation_error_deg,
      sfm_translation_error_deg: the estimated pose's errors (NaN when it failed);
      sfm_failed: 1.0 when it failed, else 0.0.
    """
    rotation = np.asarray(example["rotation"], np.float64)
    translation = np.asarray(example["translation"], np.float64)
    estimated_rotation, estimated_translation, succeeded = estimated_pose
    nan = float("nan")
    rotation_error = geometry.rotation_error_degrees(
        np.asarray(estimated_rotation, np.float64), rotation
    )
    translation_error = geometry.translation_error_degrees(
        np.asarray(estimated_translation, np.float64), translation
    )
    return {
        "baseline": float(np.linalg.norm(translation)),
        "rotation_share": rotation_share(example),
        "flow_epe_px": flow_lib.endpoint_error(
            np.asarray(example["flow"], np.float64),
            np.asarray(example["gt_flow"], np.float64),
            example["gt_flow_valid"],
        ),
        "sfm_rotation_error_deg": float(rotation_error) if succeeded else nan,
        "sfm_translation_error_deg": float(translation_error) if succeeded else nan,
        "sfm_failed": 0.0 if succeeded else 1.0,
    }


def dominant_texture(
    texture_kind: np.ndarray, valid: np.ndarray, names: Sequence[str]
) -> tuple[str, float]:
    """The texture kind covering most of the valid pixels, and its share of them.

    Args:
      texture_kind: [H, W] int, an index into `names` per pixel.
      valid: [H, W] bool, the pixels that count (e.g. the scored depth pixels).
      names: the kinds' names.

    Returns:
      (name, share); ("none", nan) without a valid pixel. A tie goes to the first kind.
    """
    texture_kind = np.asarray(texture_kind)
    valid = np.asarray(valid, bool)
    if texture_kind.shape != valid.shape:
        raise ValueError(
            f"texture_kind {texture_kind.shape} and valid {valid.shape} must have one shape"
        )
    if not valid.any():
        return "none", float("nan")
    kinds = texture_kind[valid].astype(np.int64)
    if kinds.min() < 0 or kinds.max() >= len(names):
        raise ValueError(f"texture kinds must be indices into {list(names)}, got {kinds.max()}")
    counts = np.bincount(kinds, minlength=len(names))
    index = int(np.argmax(counts))
    return names[index], float(counts[index] / kinds.size)


def quantile_bins(values: np.ndarray, num_bins: int) -> tuple[list[str], np.ndarray]:
    """Splits values into `num_bins` bins of about equal counts (terciles for 3).

    Bin k holds edges[k] <= value < edges[k + 1] (the last bin includes its upper edge),
    with the edges at the quantiles of the finite values; a non-finite value gets no bin.

    Args:
      values: [N].
      num_bins: at least 1.

    Returns:
      each value's bin label [N] ("[low, high)" with 3 significant digits, "n/a" for no
      bin; labels sort like their bins after a "k: " prefix), and the edges
      [num_bins + 1] (NaN without a finite value).
    """
    if num_bins < 1:
        raise ValueError(f"num_bins must be >= 1, got {num_bins}")
    values = np.asarray(values, np.float64)
    finite = np.isfinite(values)
    if not finite.any():
        return ["n/a"] * values.size, np.full(num_bins + 1, np.nan)
    edges = np.quantile(values[finite], np.linspace(0.0, 1.0, num_bins + 1))
    index = np.clip(np.searchsorted(edges[1:-1], values, side="right"), 0, num_bins - 1)
    names = [
        f"{k + 1}: [{edges[k]:.3g}, {edges[k + 1]:.3g}{']' if k == num_bins - 1 else ')'}"
        for k in range(num_bins)
    ]
    labels = [names[k] if ok else "n/a" for k, ok in zip(index, finite, strict=True)]
    return labels, edges


@dataclasses.dataclass(frozen=True)
class BinSummary:
    """The comparison over the pairs of one bin.

    Attributes:
      label: the bin's label.
      pairs: its number of pairs.
      model_abs_inv, reference_abs_inv: mean Abs-Inv over them of the model and of the
        reference.
      ratio: model_abs_inv / reference_abs_inv (below 1: the model is better on average).
      model_wins: the share of the pairs where the model's Abs-Inv is below the
        reference's.
    """

    label: str
    pairs: int
    model_abs_inv: float
    reference_abs_inv: float
    ratio: float
    model_wins: float


def summarise_bins(
    labels: Sequence[str], model_abs_inv: np.ndarray, reference_abs_inv: np.ndarray
) -> list[BinSummary]:
    """One `BinSummary` per label, in sorted label order, then "all" over every pair.

    Args:
      labels: [N] each pair's bin.
      model_abs_inv, reference_abs_inv: [N] per-pair Abs-Inv of each.
    """
    model_abs_inv = np.asarray(model_abs_inv, np.float64)
    reference_abs_inv = np.asarray(reference_abs_inv, np.float64)
    labels = np.asarray(labels, dtype=object)
    if not labels.shape == model_abs_inv.shape == reference_abs_inv.shape:
        raise ValueError(
            f"labels {labels.shape}, model_abs_inv {model_abs_inv.shape} and "
            f"reference_abs_inv {reference_abs_inv.shape} must be [N] alike"
        )

    def summary(label: str, members: np.ndarray) -> BinSummary:
        model_mean = float(model_abs_inv[members].mean())
        reference_mean = float(reference_abs_inv[members].mean())
        return BinSummary(
            label=label,
            pairs=int(members.sum()),
            model_abs_inv=model_mean,
            reference_abs_inv=reference_mean,
            ratio=model_mean / reference_mean if reference_mean > 0 else float("nan"),
            model_wins=float((model_abs_inv[members] < reference_abs_inv[members]).mean()),
        )

    rows = [summary(label, labels == label) for label in sorted(set(labels))]
    if labels.size:
        rows.append(summary("all", np.ones(labels.shape, bool)))
    return rows


def rank_correlation(values: np.ndarray, other: np.ndarray) -> float:
    """Spearman's rank correlation over the pairs where both are finite (ties ranked by
    their mean rank); NaN with fewer than 3 such pairs or a constant one."""
    values = np.asarray(values, np.float64)
    other = np.asarray(other, np.float64)
    both = np.isfinite(values) & np.isfinite(other)
    if both.sum() < 3:
        return float("nan")

    def ranks(array: np.ndarray) -> np.ndarray:
        _, inverse, counts = np.unique(array, return_inverse=True, return_counts=True)
        mean_rank = np.cumsum(counts) - (counts - 1) / 2.0
        return mean_rank[inverse]

    first, second = ranks(values[both]), ranks(other[both])
    if first.std() == 0 or second.std() == 0:
        return float("nan")
    return float(np.corrcoef(first, second)[0, 1])


def markdown_summary(
    tables: Mapping[str, list[BinSummary]],
    *,
    model: str,
    reference: str,
    correlations: Mapping[str, float] | None = None,
    title: str = "",
) -> str:
    """The summary as markdown: one table, a block of rows per property.

    Args:
      tables: property name -> its `summarise_bins` rows (the "all" row is shown once,
        first).
      model, reference: the compared methods' names (column heads).
      correlations: property name -> Spearman correlation of the property with the
        per-pair log(model / reference) Abs-Inv, shown in the property's first row.
      title: a first line, e.g. the dataset and the workdir.
    """
    correlations = correlations or {}
    head = (
        f"| property | ρ | bin | pairs | {model} Abs-Inv | {reference} Abs-Inv | "
        f"{model} ÷ {reference} | {model} wins |"
    )
    lines = [title, ""] if title else []
    lines += [head, "|---|---|---|---|---|---|---|---|"]

    def row(name: str, correlation: str, summary: BinSummary) -> str:
        return (
            f"| {name} | {correlation} | {summary.label} | {summary.pairs} | "
            f"{summary.model_abs_inv:.4f} | {summary.reference_abs_inv:.4f} | "
            f"{summary.ratio:.2f}× | {100 * summary.model_wins:.0f}% |"
        )

    overall = next((s for rows in tables.values() for s in rows if s.label == "all"), None)
    if overall is not None:
        lines.append(row("all pairs", "", overall))
    for name, rows in tables.items():
        heading = PROPERTIES.get(name, name.replace("_", " "))
        correlation = correlations.get(name, float("nan"))
        correlation = f"{correlation:+.2f}" if np.isfinite(correlation) else ""
        for summary in rows:
            if summary.label != "all":
                lines.append(row(heading, correlation, summary))
                heading = correlation = ""
    lines += [
        "",
        f"Bins: quantiles of the property over the pairs (ties may leave them uneven); "
        f"ratio: mean {model} Abs-Inv over mean {reference} Abs-Inv in the bin; wins: "
        f"share of the bin's pairs where {model}'s Abs-Inv is below {reference}'s; ρ: "
        f"Spearman rank correlation of the property with log({model} / {reference}) per pair "
        f"(positive: {model} fares relatively worse as the property grows).",
    ]
    return "\n".join(lines) + "\n"


def draw_regimes(
    path: str | Path,
    properties: Mapping[str, np.ndarray],
    ratios: np.ndarray,
    *,
    edges: Mapping[str, np.ndarray] | None = None,
    categories: Sequence[str] | None = None,
    model: str = "model",
    reference: str = "reference",
) -> Path:
    """One figure: per-pair Abs-Inv ratio (model / reference, log scale) against each
    continuous property (errors on a log axis, `LOG_SCALE_PROPERTIES`), with the bin edges
    dotted, and against the texture kind when `categories` are given (one panel each,
    three to a row).

    Args:
      path: the PNG to write.
      properties: name -> [N] values (the `PROPERTIES` names label their axes).
      ratios: [N] per-pair model Abs-Inv / reference Abs-Inv.
      edges: name -> its bin edges, drawn as dotted lines.
      categories: [N] each pair's texture kind, or None.
    """
    plt = reports.pyplot()
    from matplotlib import ticker

    ratios = np.asarray(ratios, np.float64)
    panels = len(properties) + (categories is not None)
    columns = min(3, panels)
    rows = -(-panels // columns)
    figure, axes = plt.subplots(rows, columns, figsize=(4.2 * columns, 3.4 * rows), squeeze=False)
    axes = list(axes.ravel())
    for axis, (name, values) in zip(axes, properties.items(), strict=False):
        values = np.asarray(values, np.float64)
        axis.scatter(values, ratios, s=9, alpha=0.6)
        for edge in (edges or {}).get(name, [])[1:-1]:
            axis.axvline(edge, color="grey", linestyle=":", linewidth=1)
        axis.set_xlabel(PROPERTIES.get(name, name))
        if name in LOG_SCALE_PROPERTIES and np.nanmin(values) > 0:
            axis.set_xscale("log")
            # Only the decades labelled: minor labels overlap on a narrow range.
            axis.xaxis.set_minor_formatter(ticker.NullFormatter())
            axis.xaxis.set_major_formatter(ticker.FormatStrFormatter("%g"))
    if categories is not None:
        axis = axes[len(properties)]
        kinds = sorted(set(categories))
        positions = np.array([kinds.index(kind) for kind in categories], np.float64)
        jitter = np.random.default_rng(0).uniform(-0.15, 0.15, positions.size)
        axis.scatter(positions + jitter, ratios, s=9, alpha=0.6)
        axis.set_xticks(range(len(kinds)), kinds)
        axis.set_xlabel("dominant texture kind")
    for axis in axes[:panels]:
        axis.set_yscale("log")
        axis.yaxis.set_major_locator(ticker.LogLocator(base=2))
        axis.yaxis.set_major_formatter(ticker.FormatStrFormatter("%g"))
        axis.yaxis.set_minor_formatter(ticker.NullFormatter())
        axis.axhline(1.0, color="black", linewidth=1)
        axis.set_ylabel(f"Abs-Inv {model} /\n{reference}")
    for axis in axes[panels:]:
        axis.axis("off")
    figure.suptitle(f"per pair: {model} / {reference} (below 1: {model} better)")
    figure.tight_layout()
    return reports.save_figure(figure, path)
