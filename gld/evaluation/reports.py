"""Evaluation reports: metrics.json, table.md, per-example CSVs and example figures.

`write_report` writes the numbers of several methods evaluated on the same examples
(`gld.evaluation.evaluate`), with the references' labels (the oracle sees the truth; the
classical pipeline runs on the same flow, with no training), each method's Abs-Inv as a
multiple of the dataset mean's, the pixels its predictions had excluded and the pairs a
method failed on, and the protocol the evaluated records were built with (a DeMoN
dataset's WebP decoder, depth resampling and order); `render_examples` draws image,
truth, prediction and error with one colour scale for all.
"""

from __future__ import annotations

import csv
import json
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from gld.evaluation import metrics
from gld.models.baselines import classical


def pyplot():
    """matplotlib's pyplot on the Agg backend: figures go to files, never to a display."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def save_figure(figure, path: str | Path, *, dpi: int = 100) -> Path:
    """Writes a figure as PNG (its folder created, the margins trimmed) and closes it."""
    import matplotlib.pyplot as plt

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    figure.savefig(path, dpi=dpi, bbox_inches="tight")
    plt.close(figure)
    return path


def write_report(
    out_dir: str | Path,
    results: dict[str, tuple[dict[str, np.ndarray], list[str]]],
    *,
    height: int,
    width: int,
    info: dict[str, Any] | None = None,
    protocol_note: str = "",
    truth_resolution: str = "record",
    file_resolutions: dict[str, int] | None = None,
    records_protocol: Mapping[str, Any] | None = None,
) -> dict[str, Any]:
    """Writes metrics.json, table.md and per_example_<method>.csv for several methods.

    Methods appear in the order of `results`; the references are labelled
    (`gld.models.baselines.classical.LABELS`: the oracle sees the ground truth, the classical
    pipeline is untrained) in the table and in metrics.json, which also holds each
    method's Abs-Inv as a multiple of the dataset mean's when the dataset mean is among
    the methods, and the pixels each method's predictions had excluded
    (`metrics.excluded_pixels`). Under the table, table.md says which pixels were
    excluded and, for a method with a per-example "failed" value (the classical
    pipeline), on how many pairs it failed. A per_example_<method>.csv of a method not
    in `results` (left by an earlier evaluation in `out_dir`) is removed, so that the
    folder holds the rows of one evaluation only.

    Args:
      out_dir: the directory (created).
      results: method name -> (per-example metrics incl. "example_mask", ids).
      height, width: the records' resolution, for the protocol stamp.
      info: extra fields for metrics.json (dataset, split, step, ...).
      protocol_note: appended to the protocol stamp (e.g. how stored predictions were read).
      truth_resolution, file_resolutions: where the ground truth was scored, for the
        stamp (`metrics.protocol_stamp`).
      records_protocol: the build options that make the records' protocol (e.g. a DeMoN
        dataset's {"image_decoder": ..., "depth_resampling": ..., "order": ...}): in
        metrics.json as "records_protocol", and in the stamp, whose last clause
        (`metrics.records_protocol_note`) names them.

    Returns:
      The metrics.json content.
    """

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    for stale in out_dir.glob("per_example_*.csv"):
        if stale.stem.removeprefix("per_example_") not in results:
            stale.unlink()
    summaries = {}
    num_examples = 0
    for method, (per_example, ids) in results.items():
        per_example = dict(per_example)
        mask = per_example.pop("example_mask").astype(bool)
        num_examples = int(mask.sum())
        summaries[method] = metrics.summarise(per_example, mask)
        with (out_dir / f"per_example_{method}.csv").open("w", newline="") as stream:
            writer = csv.writer(stream)
            names = sorted(per_example)
            writer.writerow(["id", *names])
            for row, example_id in enumerate(ids):
                if mask[row]:
                    writer.writerow([example_id, *(f"{per_example[n][row]:.6g}" for n in names)])
    stamp = metrics.protocol_stamp(
        height,
        width,
        num_examples,
        extra=protocol_note,
        truth_resolution=truth_resolution,
        file_resolutions=file_resolutions,
        records_protocol=records_protocol,
    )
    labels = {name: label for name, label in classical.LABELS.items() if name in summaries}
    excluded = {method: metrics.excluded_pixels(summary) for method, summary in summaries.items()}
    report = {
        "protocol": stamp,
        **(info or {}),
        **({"records_protocol": dict(records_protocol)} if records_protocol else {}),
        "methods": summaries,
        "labels": labels,
        "abs_inv_vs_dataset_mean": metrics.ratios_to_reference(summaries.items()),
        "excluded_pixels": {
            method: value for method, value in excluded.items() if value is not None
        },
    }
    (out_dir / "metrics.json").write_text(json.dumps(report, indent=2) + "\n")
    table = metrics.markdown_table(summaries.items(), stamp, labels=labels)
    failures = failure_note(summaries)
    if failures:
        table += f"\n{failures}\n"
    (out_dir / "table.md").write_text(table)
    return report


def failure_note(summaries: dict[str, dict[str, dict]]) -> str:
    """One line giving, for each method with a per-example "failed" value (1 where the
    method gave up on a pair and predicted its fallback constant), its failed pairs ("" if
    no method has one)."""
    parts = [
        f"{method} {round(summary['failed']['mean'] * summary['failed']['count'])} of "
        f"{summary['failed']['count']}"
        for method, summary in summaries.items()
        if summary.get("failed", {}).get("count")
    ]
    if not parts:
        return ""
    return "Failed pairs (predicted as the method's fallback constant): " + "; ".join(parts) + "."


def render_examples(
    out_dir: str | Path,
    examples: Sequence[dict[str, np.ndarray]],
    predictions: Sequence[np.ndarray],
    *,
    max_inv_depth: float | None = None,
) -> list[Path]:
    """One PNG per example: image 1, ground truth, prediction, |error| (inverse depth).

    All panels of all examples share one colour scale (`max_inv_depth`, by default the
    99th percentile of the ground truth over the examples); the supervised pixels
    (`sparse_mask`) are circled on image 1.
    """
    plt = pyplot()
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    truths = [
        np.where(e["depth_valid"], 1.0 / np.where(e["depth_valid"], e["depth"], 1), np.nan)
        for e in examples
    ]
    if max_inv_depth is None:
        values = np.concatenate([t[np.isfinite(t)] for t in truths] or [np.ones(1)])
        max_inv_depth = float(np.percentile(values, 99)) if values.size else 1.0
    paths = []
    for example, truth, prediction in zip(examples, truths, predictions, strict=True):
        inv_prediction = 1.0 / np.asarray(prediction)
        error = np.where(np.isfinite(truth), np.abs(inv_prediction - truth), np.nan)
        figure, axes = plt.subplots(1, 4, figsize=(14, 3.0))
        axes[0].imshow(np.clip(example["image1"] + 0.5, 0, 1))
        supervised_v, supervised_u = np.nonzero(example.get("sparse_mask", np.zeros(1, bool)))
        axes[0].scatter(supervised_u, supervised_v, s=60, facecolors="none", edgecolors="red")
        axes[0].set_title("image 1 (supervised pixel circled)")
        for axis, data, title in (
            (axes[1], truth, "ground truth 1/depth"),
            (axes[2], inv_prediction, "prediction 1/depth"),
            (axes[3], error, "|error|"),
        ):
            shown = axis.imshow(data, cmap="magma", vmin=0.0, vmax=max_inv_depth)
            axis.set_title(title)
        figure.colorbar(shown, ax=axes[1:].tolist(), fraction=0.02)
        for axis in axes:
            axis.set_axis_off()
        name = str(example["id"]).replace("/", "_")
        path = out_dir / f"{name}.png"
        paths.append(save_figure(figure, path, dpi=80))
    return paths
