"""Scoring the learned flow network against the records' exact flow, next to the stored
estimated flow (OpenCV DIS for gld_scenes), on the same pairs and valid pixels.

    per_example, ids, summary = evaluate_flow(model, variables, test_source)

`evaluate_flow` runs `make_flow_eval_step` over a split (end-point error, outliers above
`OUTLIER_PIXELS`); `write_flow_report` writes `flow.json` and `flow_table.md` with the
parameters and the forward latency (`forward_latency`); `report_trained_flow` is the
final evaluation of a trained network, all three in one.
"""

from __future__ import annotations

import json
import statistics
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh

from gld import files as files_lib
from gld import sharding
from gld.evaluation import evaluate as evaluation
from gld.models.flow_net import FlowNet, parameter_count

# Evaluation batches also carry the stored estimated flow ("flow") to score it alike.
FLOW_EVAL_KEYS = ("image1", "image2", "flow", "gt_flow", "gt_flow_valid", "example_mask")


# End-point errors above this many pixels count as outliers (KITTI's Fl uses 3 px too).
OUTLIER_PIXELS = 3.0


# The stored estimated flow's name in reports (gld_scenes stores OpenCV DIS).
STORED_FLOW = "dis"


NETWORK = "flow_net"


def make_flow_eval_step(*, model: FlowNet) -> Callable[[dict, dict], dict]:
    """Builds the pure `eval_step(variables, batch) -> per-example values` ([B] each):
    mean end-point error and outlier fraction of the network and of the batch's stored
    flow ("flow") over the same valid pixels, the pixel count and "example_mask" (real
    rows with at least one valid pixel)."""

    def eval_step(variables: dict, batch: dict) -> dict:
        flow = model.apply(variables, batch["image1"], batch["image2"])["flow"]
        valid = batch["gt_flow_valid"]
        count = jnp.sum(valid, axis=(1, 2))
        values = {"valid_pixels": count}
        for name, estimate in ((NETWORK, flow), (STORED_FLOW, batch["flow"])):
            errors = jnp.linalg.norm(estimate - batch["gt_flow"], axis=-1)
            sums = jnp.sum(jnp.where(valid, errors, 0.0), axis=(1, 2))
            outliers = jnp.sum(valid & (errors > OUTLIER_PIXELS), axis=(1, 2))
            values[f"{name}_epe"] = sums / jnp.maximum(count, 1)
            values[f"{name}_epe_sum"] = sums
            values[f"{name}_outliers"] = outliers / jnp.maximum(count, 1)
        values["example_mask"] = batch["example_mask"] & (count > 0)
        return values

    return eval_step


def summarise_flow(per_example: dict[str, np.ndarray]) -> dict[str, dict[str, float]]:
    """method -> {"epe" (mean over pairs of each pair's mean EPE), "epe_std",
    "epe_median", "epe_pixels" (mean over all valid pixels), "outliers" (mean fraction
    of pixels with EPE > OUTLIER_PIXELS), "count" (pairs)}."""
    mask = np.asarray(per_example["example_mask"], bool)
    pixels = np.asarray(per_example["valid_pixels"], np.float64)[mask]
    summary = {}
    for name in (NETWORK, STORED_FLOW):
        epe = np.asarray(per_example[f"{name}_epe"], np.float64)[mask]
        sums = np.asarray(per_example[f"{name}_epe_sum"], np.float64)[mask]
        outliers = np.asarray(per_example[f"{name}_outliers"], np.float64)[mask]
        empty = not mask.any()
        summary[name] = {
            "epe": float("nan") if empty else float(epe.mean()),
            "epe_std": float("nan") if empty else float(epe.std()),
            "epe_median": float("nan") if empty else float(np.median(epe)),
            "epe_pixels": float("nan") if empty else float(sums.sum() / pixels.sum()),
            "outliers": float("nan") if empty else float(outliers.mean()),
            "count": int(mask.sum()),
        }
    return summary


def evaluate_flow(
    model: FlowNet,
    variables: dict,
    source,
    *,
    batch_size: int = 16,
    max_examples: int = 0,
    mesh: Mesh | None = None,
    eval_step: Callable | None = None,
    progress: bool = False,
) -> tuple[dict[str, np.ndarray], list[str], dict[str, dict[str, float]]]:
    """End-point errors of the network and of the records' stored estimated flow (DIS
    for gld_scenes) against `gt_flow`, on the same pairs and `gt_flow_valid` pixels.

    Args:
      model, variables: the network and its trained variables.
      source: random-access records (a TFDS data source of a split).
      batch_size: pairs per evaluation batch (rounded up to the devices).
      max_examples: the first N records only; 0 = all.
      mesh: devices to run on (default: all).
      eval_step: a compiled `make_flow_eval_step` to reuse (periodic evaluation).
      progress: show a progress bar.

    Returns:
      (per-example values as `make_flow_eval_step` names them, [N] each, padded rows
      masked out; the pairs' ids; `summarise_flow` of them).
    """
    mesh = mesh or sharding.make_mesh()
    batch_size = sharding.evaluation_batch_size(batch_size, mesh)
    local_batch = sharding.per_process_batch_size(batch_size, mesh)
    variables = jax.device_put(variables, sharding.replicated(mesh))
    eval_step = eval_step or evaluation.jit_eval_step(make_flow_eval_step(model=model), mesh)

    def score(batch, ids):
        del ids
        device_batch = sharding.to_global_batch(batch, mesh, FLOW_EVAL_KEYS)
        return sharding.gather(eval_step(variables, device_batch))

    batches = evaluation.split_batches(
        source,
        batch_size=local_batch,
        flow_source="estimated",
        max_examples=max_examples,
        keys=FLOW_EVAL_KEYS,
        progress=progress,
    )
    per_example, ids = evaluation.evaluate_batches(batches, score)
    return per_example, ids, summarise_flow(per_example)


def forward_latency(
    model: FlowNet, variables: dict, height: int, width: int, *, repeats: int = 30
) -> dict[str, float]:
    """Wall-clock time of one compiled forward pass at batch 1 (after a warm-up call):
    {"median_ms", "p90_ms", "repeats"}. For reports; speed claims are measured, not
    asserted."""
    if repeats < 1:
        raise ValueError(f"repeats must be >= 1, got {repeats}")
    forward = jax.jit(lambda variables, image1, image2: model.apply(variables, image1, image2))
    images = jax.random.uniform(jax.random.key(0), (2, 1, height, width, 3)) - 0.5
    jax.block_until_ready(forward(variables, images[0], images[1]))
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        jax.block_until_ready(forward(variables, images[0], images[1]))
        times.append(time.perf_counter() - start)
    times.sort()
    return {
        "median_ms": 1e3 * statistics.median(times),
        "p90_ms": 1e3 * times[min(len(times) - 1, int(0.9 * len(times)))],
        "repeats": repeats,
    }


def write_flow_report(
    out_dir: str | Path,
    summary: dict[str, dict[str, float]],
    *,
    parameters: int,
    latency: dict[str, float],
    info: dict[str, Any],
) -> str:
    """Writes `flow.json` and `flow_table.md` into `out_dir` (process 0); returns the
    table's text.

    Args:
      summary: `summarise_flow`'s result.
      parameters: the network's parameter count.
      latency: `forward_latency`'s result.
      info: what was evaluated ("dataset", "split", "step", "height", "width", ...).
    """
    out_dir = Path(out_dir)
    network, stored = summary[NETWORK], summary[STORED_FLOW]
    ratio = network["epe"] / stored["epe"] if stored["epe"] else float("nan")
    report = {
        **info,
        "protocol": (
            "end-point error (pixels) against the records' gt_flow over gt_flow_valid pixels; "
            "epe: mean over pairs of each pair's mean; epe_pixels: mean over all valid "
            f"pixels; outliers: fraction of pixels with EPE > {OUTLIER_PIXELS:g} px"
        ),
        "methods": summary,
        "epe_vs_dis": ratio,
        "parameters": parameters,
        "latency_batch1": {**latency, "device": str(jax.devices()[0].device_kind)},
    }
    where = f"{info.get('dataset', '')} {info.get('split', '')}".strip()
    lines = [
        f"Optical flow on {where}, {network['count']} pairs at "
        f"{info.get('width')}x{info.get('height')} (step {info.get('step')})",
        "",
        "| method | EPE (px) | ± std | median | EPE pixel-mean | > 3 px | parameters | ms/pair |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for name, label, params, milliseconds in (
        (NETWORK, "flow_net (learned, PWC-Net style)", f"{parameters:,}", latency["median_ms"]),
        (STORED_FLOW, "dis (stored estimated flow, OpenCV DIS)", "—", None),
    ):
        row = summary[name]
        lines.append(
            f"| {label} | {row['epe']:.3f} | {row['epe_std']:.3f} | {row['epe_median']:.3f} | "
            f"{row['epe_pixels']:.3f} | {100 * row['outliers']:.1f}% | {params} | "
            + (f"{milliseconds:.1f} |" if milliseconds is not None else "— |")
        )
    lines += [
        "",
        f"EPE of the network ÷ EPE of DIS: {ratio:.3f}. ms/pair: median forward at batch 1 "
        f"on {report['latency_batch1']['device']}.",
    ]
    table = "\n".join(lines) + "\n"
    if jax.process_index() == 0:
        out_dir.mkdir(parents=True, exist_ok=True)
        files_lib.write_atomically(out_dir / "flow.json", json.dumps(report, indent=2) + "\n")
        files_lib.write_atomically(out_dir / "flow_table.md", table)
    return table


def report_trained_flow(
    model: FlowNet,
    variables: dict,
    test_source,
    out_dir: str | Path,
    *,
    info: dict[str, Any],
    batch_size: int = 16,
    latency_repeats: int = 30,
    progress: bool = True,
) -> str:
    """The final evaluation of a trained flow network: its end-point error and the stored
    flow's on the whole test split (`evaluate_flow`), its parameters and its batch-1
    latency (`forward_latency`), written as `flow.json` and `flow_table.md`
    (`write_flow_report`); returns the table.

    Args:
      info: what was evaluated: "dataset", "split", "step", "height", "width".
    """
    _, _, summary = evaluate_flow(
        model, variables, test_source, batch_size=batch_size, progress=progress
    )
    latency = forward_latency(
        model, variables, info["height"], info["width"], repeats=latency_repeats
    )
    return write_flow_report(
        out_dir,
        summary,
        parameters=parameter_count(variables["params"]),
        latency=latency,
        info=info,
    )
