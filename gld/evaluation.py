"""Evaluation reports: metrics.json, table.md, a per-example CSV and example figures.

Learned models are evaluated by `gld.train.evaluate_source` (jit, sharded, exact means
over padded batches); methods without parameters (the classical baselines) by
`evaluate_predictor`, which runs any `predict(batch) -> {"depth", ...}` on the host.
Every report carries its references on the same split: the dataset mean and the
per-pair oracle constant, with each method's Abs-Inv as a multiple of the dataset mean's.
"""

from __future__ import annotations

import csv
import json
import math
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import jax
import numpy as np

from gld import input_pipeline, metrics

# The per-pair oracle constant reported next to every method (`classical.OraclePairMedian`).
ORACLE = "oracle_pair_median"


def evaluate_predictor(
    predict: Callable[[dict[str, np.ndarray]], dict[str, Any]],
    source,
    *,
    batch_size: int = 16,
    flow: str = "estimated",
    max_examples: int = 0,
    progress: bool = False,
) -> tuple[dict[str, np.ndarray], list[str]]:
    """Per-example metrics of a host-side predictor over a split (single process).

    `predict` gets an example-contract batch (numpy) and returns at least "depth"
    [B, H, W]; any other [B]-shaped outputs (e.g. "failed") are kept per example.
    """
    if max_examples:
        source = [source[i] for i in range(min(max_examples, len(source)))]
    batches = input_pipeline.eval_batches(source, batch_size=batch_size, flow_source=flow)
    if progress:
        from tqdm import tqdm

        batches = tqdm(
            batches,
            total=math.ceil(len(source) / batch_size),
            desc="evaluate",
            unit="batch",
            leave=False,
        )
    depth_metrics = jax.jit(metrics.depth_metrics)
    collected: dict[str, list] = {}
    ids: list[str] = []
    for batch in batches:
        outputs = predict(batch)
        per_example = {
            k: np.asarray(v)
            for k, v in depth_metrics(
                outputs["depth"], batch["depth"], batch["depth_valid"]
            ).items()
        }
        per_example["example_mask"] = np.asarray(batch["example_mask"]) & (
            per_example["num_pixels"] > 0
        )
        for key, value in outputs.items():
            value = np.asarray(value)
            if key not in per_example and value.shape == (len(batch["id"]),):
                per_example[key] = value.astype(np.float64)
        for key, value in per_example.items():
            collected.setdefault(key, []).append(value)
        ids.extend(str(i) for i in batch["id"])
    return {k: np.concatenate(v) for k, v in collected.items()}, ids


def write_report(
    out_dir: str | Path,
    results: dict[str, tuple[dict[str, np.ndarray], list[str]]],
    *,
    height: int,
    width: int,
    info: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """Writes metrics.json, table.md and per_example_<method>.csv for several methods.

    Methods appear in the order of `results`; references that see the ground truth are
    labelled (`gld.baselines.classical.LABELS`) in the table and in metrics.json, which
    also holds each method's Abs-Inv as a multiple of the dataset mean's when the
    dataset mean is among the methods.

    Args:
      out_dir: the directory (created).
      results: method name -> (per-example metrics incl. "example_mask", ids).
      height, width: evaluation resolution, for the protocol stamp.
      info: extra fields for metrics.json (dataset, split, step, ...).

    Returns:
      The metrics.json content.
    """
    from gld.baselines import classical

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
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
    stamp = metrics.protocol_stamp(height, width, num_examples)
    labels = {name: label for name, label in classical.LABELS.items() if name in summaries}
    report = {
        "protocol": stamp,
        **(info or {}),
        "methods": summaries,
        "labels": labels,
        "abs_inv_vs_dataset_mean": metrics.ratios_to_reference(summaries.items()),
    }
    (out_dir / "metrics.json").write_text(json.dumps(report, indent=2) + "\n")
    table = metrics.markdown_table(summaries.items(), stamp, labels=labels)
    (out_dir / "table.md").write_text(table)
    return report


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
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

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
        figure.savefig(path, dpi=80, bbox_inches="tight")
        plt.close(figure)
        paths.append(path)
    return paths


def _training_batches(train_source, flow: str):
    return input_pipeline.eval_batches(train_source, batch_size=16, flow_source=flow)


def fit_classical(name: str, train_source, flow: str = "estimated"):
    """A classical baseline by name, fitted on the training split when it needs to be."""
    from gld.baselines import classical

    if name not in classical.CLASSICAL:
        raise ValueError(f"unknown classical method {name!r}; valid: {sorted(classical.CLASSICAL)}")
    method = classical.CLASSICAL[name]()
    if method.needs_training_data:
        method.fit(
            {key: batch[key][batch["example_mask"]] for key in ("depth", "depth_valid")}
            for batch in _training_batches(train_source, flow)
        )
    return method


def _figure_examples(source, count: int, gt_pixels: int, seed: int, flow: str, split: str):
    return [
        input_pipeline.prepare_example(
            source[index],
            epoch=0,
            seed=seed,
            gt_pixels=gt_pixels,
            flow_source=flow,
            augment=False,
            fixed_sparse_pixels=True,
            where=f"{split}[{index}]",
        )
        for index in range(min(count, len(source)))
    ]


def evaluate_workdir(
    workdir: str | Path,
    source,
    *,
    train_source=None,
    dataset: str = "",
    height: int,
    width: int,
    split: str = "test",
    num_figures: int = 8,
    with_dataset_mean: bool = True,
    with_oracle: bool = True,
    batch_size: int = 16,
    max_examples: int = 0,
    step: int | None = None,
    classical_method: str | None = None,
    flow: str | None = None,
    print_fn: Callable[[str], None] = print,
) -> dict[str, Any]:
    """Evaluates a workdir's trained model (or a classical method) on `source`.

    Writes <workdir>/eval (see `write_report` and `render_examples`). The references are
    evaluated alongside on the same examples with the same flow, when asked: the dataset
    mean (fitted on `train_source`, so only when it is given) and the per-pair oracle
    constant. Rows: the method, then dataset_mean, then oracle_pair_median.
    """
    from gld import train

    results, info = {}, {"dataset": dataset, "split": split}
    if classical_method:
        flow = flow or "estimated"
        method = fit_classical(classical_method, train_source, flow)
        results[classical_method] = evaluate_predictor(
            method.predict,
            source,
            batch_size=batch_size,
            flow=flow,
            max_examples=max_examples,
            progress=True,
        )
        predict_depth = lambda batch: method.predict(batch)["depth"]  # noqa: E731
        gt_pixels, seed = 1, 0
        info.update(model=classical_method, flow=flow)
    else:
        model, variables, config = train.load_trained(workdir, step=step)
        flow = flow or config.flow
        results[config.model] = train.evaluate_source(
            model,
            variables,
            source,
            batch_size=batch_size,
            flow=flow,
            max_examples=max_examples,
            progress=True,
        )
        apply = jax.jit(lambda v, b: model.apply(v, b["image1"], b["image2"], b["flow"]))
        predict_depth = lambda batch: apply(variables, batch)["depth"]  # noqa: E731
        gt_pixels, seed = config.gt_pixels, config.seed
        manager = train.checkpoint_manager(workdir)
        info.update(
            model=config.model,
            gt_pixels=config.gt_pixels,
            flow=flow,
            step=int(manager.latest_step() if step is None else step),
        )
        manager.close()
    if with_dataset_mean and train_source is not None and jax.process_index() == 0:
        mean = fit_classical("dataset_mean", train_source, flow)
        results["dataset_mean"] = evaluate_predictor(
            mean.predict, source, batch_size=batch_size, flow=flow, max_examples=max_examples
        )
        info["dataset_mean_inv_depth"] = mean.inv_depth
    if with_oracle and classical_method != ORACLE and jax.process_index() == 0:
        oracle = fit_classical(ORACLE, train_source, flow)
        results[ORACLE] = evaluate_predictor(
            oracle.predict, source, batch_size=batch_size, flow=flow, max_examples=max_examples
        )
    if jax.process_index() != 0:
        return {}
    out_dir = Path(workdir) / "eval"
    report = write_report(out_dir, results, height=height, width=width, info=info)
    if num_figures:
        examples = _figure_examples(source, num_figures, gt_pixels, seed, flow, split)
        batch = {
            key: np.stack([example[key] for example in examples])
            for key, value in examples[0].items()
            if isinstance(value, np.ndarray)
        }
        predictions = np.asarray(predict_depth(batch))
        render_examples(out_dir / "figures", examples, list(predictions))
    print_fn((out_dir / "table.md").read_text())
    return report
