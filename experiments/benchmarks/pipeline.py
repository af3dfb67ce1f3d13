"""Throughput of the training input pipeline (gld.input_pipeline) against the trainer's needs.

    python -m experiments.benchmarks.pipeline                          # gld_scenes/small
    python -m experiments.benchmarks.pipeline --dataset=gld_scenes/tiny --workers=0,1

Measures examples per second of `train_dataset` (decode, augmentation, scale
normalisation, sparse sampling, batching) for several grain worker counts, and
compares each with what the train step consumes: `batch_size / train_step_s`
examples per second. The trainer never waits for data when the pipeline is several
times faster (the target is 5x). The machine may be shared, so rates are noisy.
"""

from __future__ import annotations

import time
from typing import Any

from absl import flags

import data
from data import command_line
from experiments.benchmarks import format_table
from gld import input_pipeline

FLAGS = flags.FLAGS

# The target ratio of pipeline throughput to the trainer's consumption.
TARGET_RATIO = 5.0


def measure(
    source,
    *,
    batch_size: int,
    num_batches: int,
    worker_count: int,
    gt_pixels: int = 1,
    seed: int = 0,
) -> dict[str, float]:
    """Times one `train_dataset` configuration with augmentation.

    Returns:
      `startup_s` (iterator creation to the first batch: worker start-up and filling
      the buffers), `examples_per_s` (wall clock) over the next `num_batches` batches
      and `examples_per_cpu_s`, examples per CPU-second of this process: with 0 workers
      all the work is here, so it is the rate of one otherwise idle core.
    """
    dataset = input_pipeline.train_dataset(
        source,
        batch_size=batch_size,
        seed=seed,
        gt_pixels=gt_pixels,
        augment=True,
        worker_count=worker_count,
    )
    start = time.perf_counter()
    iterator = iter(dataset)
    try:
        next(iterator)
        startup_s = time.perf_counter() - start
        start, start_cpu = time.perf_counter(), time.process_time()
        for _ in range(num_batches):
            batch = next(iterator)
        elapsed = time.perf_counter() - start
        elapsed_cpu = time.process_time() - start_cpu
        if batch["image1"].shape[0] != batch_size:
            raise RuntimeError(f"expected batches of {batch_size}, got {batch['image1'].shape}")
    finally:
        if hasattr(iterator, "close"):
            iterator.close()
    examples = num_batches * batch_size
    return {
        "startup_s": startup_s,
        "examples_per_s": examples / elapsed,
        "examples_per_cpu_s": examples / elapsed_cpu,
    }


def run(
    *,
    dataset: str = "gld_scenes/small",
    data_dir: str | None = None,
    split: str = "train",
    batch_size: int = 16,
    num_batches: int = 40,
    workers: tuple[int, ...] = (0, 1, 2),
    train_step_s: float = 0.3,
    gt_pixels: int = 1,
    skip_unused: bool = False,
) -> dict[str, Any]:
    """Measures the pipeline for each worker count and compares it with the trainer.

    Args:
      dataset: 'name/config', built on first use under `data_dir`.
      data_dir: where datasets live (default: the project's default).
      split: the split read.
      batch_size: examples per batch (the trainer's per-process batch).
      num_batches: batches timed per worker count (after the first).
      workers: grain worker process counts to measure (0 = in this process).
      train_step_s: seconds per train step at `batch_size`; the default is the fast
        end of the CPU trainer (0.3-1.5 s), the demanding case.
      gt_pixels: supervised pixels per example.
      skip_unused: read the source with `input_pipeline.source_decoders()` (fields
        the pipeline never uses stay undecoded).

    Returns:
      A flat dict: the settings, `consumption_examples_per_s` of the trainer, and per
      worker count n `examples_per_s_w{n}`, `startup_s_w{n}`, `ratio_w{n}` (pipeline /
      consumption) and `meets_target_w{n}` (ratio >= 5); `examples_per_cpu_s_w0`.
    """
    builder = data.prepare(dataset, data_dir)
    decoders = input_pipeline.source_decoders() if skip_unused else None
    source = builder.as_data_source(split, decoders=decoders)
    height, width = builder.info.features["depth1"].shape
    consumption = batch_size / train_step_s
    results: dict[str, Any] = {
        "dataset": dataset,
        "split": split,
        "examples": len(source),
        "resolution": f"{width}x{height}",
        "skip_unused": skip_unused,
        "batch_size": batch_size,
        "num_batches": num_batches,
        "train_step_s": train_step_s,
        "consumption_examples_per_s": consumption,
    }
    for worker_count in workers:
        figures = measure(
            source,
            batch_size=batch_size,
            num_batches=num_batches,
            worker_count=worker_count,
            gt_pixels=gt_pixels,
        )
        ratio = figures["examples_per_s"] / consumption
        results[f"examples_per_s_w{worker_count}"] = figures["examples_per_s"]
        results[f"startup_s_w{worker_count}"] = figures["startup_s"]
        if worker_count == 0:
            results["examples_per_cpu_s_w0"] = figures["examples_per_cpu_s"]
        results[f"ratio_w{worker_count}"] = ratio
        results[f"meets_target_w{worker_count}"] = bool(ratio >= TARGET_RATIO)
    return results


def _define_flags() -> None:
    # Defined only when run as a script, so importing `run` defines no global flags.
    flags.DEFINE_string("dataset", "gld_scenes/small", "Dataset 'name/config' to read.")
    flags.DEFINE_string("data_dir", None, "Where datasets live (default: ./datasets).")
    flags.DEFINE_string("split", "train", "Split to read.")
    flags.DEFINE_integer("batch_size", 16, "Per-process batch size.")
    flags.DEFINE_integer("num_batches", 40, "Batches timed per worker count.")
    flags.DEFINE_list("workers", ["0", "1", "2"], "grain worker process counts.")
    flags.DEFINE_float("train_step_s", 0.3, "Seconds per train step at --batch_size.")
    flags.DEFINE_integer("gt_pixels", 1, "Supervised pixels per example.")
    flags.DEFINE_bool("skip_unused", False, "Leave fields the pipeline never reads undecoded.")


def main(argv: list[str]) -> None:
    del argv
    results = run(
        dataset=FLAGS.dataset,
        data_dir=FLAGS.data_dir,
        split=FLAGS.split,
        batch_size=FLAGS.batch_size,
        num_batches=FLAGS.num_batches,
        workers=tuple(int(count) for count in FLAGS.workers),
        train_step_s=FLAGS.train_step_s,
        gt_pixels=FLAGS.gt_pixels,
        skip_unused=FLAGS.skip_unused,
    )
    print(format_table(results))


if __name__ == "__main__":
    _define_flags()
    command_line.run(main)
