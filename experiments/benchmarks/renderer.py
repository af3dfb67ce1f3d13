"""Throughput of the gld_scenes renderer and build time of a gld_scenes config.

    python -m experiments.benchmarks.renderer                     # 256x192, small build
    python -m experiments.benchmarks.renderer --build_config=tiny --num_pairs=20

Reports wall-clock rates and, because the machine may be shared, CPU-time rates of
this process (the rate an otherwise idle core would reach).
"""

from __future__ import annotations

import multiprocessing
import shutil
import tempfile
import time
from pathlib import Path
from typing import Any

from absl import flags

import data
from data import command_line
from data.gld_scenes import example_records, renderer, scene_configs, scenes
from experiments.benchmarks import format_table
from gld import flow

FLAGS = flags.FLAGS


def _timed(function, count: int) -> tuple[float, float]:
    """(wall seconds, CPU seconds of this process) of `count` calls of `function(i)`."""
    wall, cpu = time.perf_counter(), time.process_time()
    for index in range(count):
        function(index)
    return time.perf_counter() - wall, time.process_time() - cpu


def _directory_bytes(path: Path) -> int:
    return sum(file.stat().st_size for file in path.rglob("*") if file.is_file())


def run(
    *,
    height: int = 192,
    width: int = 256,
    num_pairs: int = 40,
    workers: tuple[int, ...] = (1, 2),
    build_config: str | None = "small",
    build_workers: int = 1,
    data_dir: str | None = None,
) -> dict[str, Any]:
    """Measures the renderer and, optionally, a full build.

    Args:
      height, width: render size of the throughput measurements.
      num_pairs: pairs rendered per measurement.
      workers: process counts for the render + DIS flow throughput (1 = this process).
      build_config: a gld_scenes config to build from scratch and time (None skips it).
      build_workers: processes for that build.
      data_dir: where to build (default: a temporary directory, removed afterwards).

    Returns:
      A flat dict of figures: `render_pairs_per_s` (render only, wall and CPU),
      `dis_pairs_per_s_w{n}` (render + DIS flow + encoding as the builder does),
      `dis_ms`, and for the build `build_s`, `build_bytes`, `flow_epe_test`.
    """
    settings = scenes.SceneSettings(height=height, width=width)
    config = scene_configs.SceneConfig(name="benchmark", height=height, width=width)
    results: dict[str, Any] = {"height": height, "width": width, "num_pairs": num_pairs}

    renderer.render_pair(renderer.example_rng(0, "warmup", 0), settings)
    wall, cpu = _timed(
        lambda index: renderer.render_pair(renderer.example_rng(0, "bench", index), settings),
        num_pairs,
    )
    results["render_pairs_per_s"] = num_pairs / wall
    results["render_pairs_per_cpu_s"] = num_pairs / cpu

    tasks = [(config, "bench", index) for index in range(num_pairs)]
    for count in workers:
        if count == 1:
            wall, cpu = _timed(lambda index: example_records.render_record(tasks[index]), num_pairs)
            results["dis_pairs_per_s_w1"] = num_pairs / wall
            results["dis_pairs_per_cpu_s_w1"] = num_pairs / cpu
        else:
            with multiprocessing.get_context("fork").Pool(count) as pool:
                pool.map(example_records.render_record, tasks[:count])  # start the workers
                wall = time.perf_counter()
                list(pool.imap(example_records.render_record, tasks, chunksize=4))
                results[f"dis_pairs_per_s_w{count}"] = num_pairs / (time.perf_counter() - wall)

    example = renderer.render_pair(renderer.example_rng(0, "bench", 0), settings)
    wall, cpu = _timed(lambda _: flow.estimate(example["image1"], example["image2"]), 20)
    results["dis_ms"] = 1000 * cpu / 20

    if build_config is not None:
        root = Path(data_dir) if data_dir else Path(tempfile.mkdtemp(prefix="gld_scenes_bench"))
        try:
            wall, cpu = time.perf_counter(), time.process_time()
            builder = data.prepare(f"gld_scenes/{build_config}", root, workers=build_workers)
            results["build_config"] = build_config
            results["build_s"] = time.perf_counter() - wall
            results["build_cpu_s"] = time.process_time() - cpu
            results["build_bytes"] = _directory_bytes(Path(builder.data_path))
            results["build_examples"] = sum(
                split.num_examples for split in builder.info.splits.values()
            )
            results["flow_epe_test"] = builder.info.metadata["flow_epe_test"]
        finally:
            if not data_dir:
                shutil.rmtree(root, ignore_errors=True)
    return results


def _define_flags() -> None:
    # Defined only when run as a script, so importing `run` defines no global flags.
    flags.DEFINE_integer("height", 192, "Render height of the throughput measurements.")
    flags.DEFINE_integer("width", 256, "Render width of the throughput measurements.")
    flags.DEFINE_integer("num_pairs", 40, "Pairs rendered per measurement.")
    flags.DEFINE_list("workers", ["1", "2"], "Process counts for render + DIS throughput.")
    flags.DEFINE_string("build_config", "small", "gld_scenes config to build; 'none' skips.")
    flags.DEFINE_integer("build_workers", 1, "Processes for the build.")
    flags.DEFINE_string("data_dir", None, "Build directory (default: a temporary one).")


def main(argv: list[str]) -> None:
    del argv
    results = run(
        height=FLAGS.height,
        width=FLAGS.width,
        num_pairs=FLAGS.num_pairs,
        workers=tuple(int(count) for count in FLAGS.workers),
        build_config=None if FLAGS.build_config == "none" else FLAGS.build_config,
        build_workers=FLAGS.build_workers,
        data_dir=FLAGS.data_dir,
    )
    print(format_table(results))


if __name__ == "__main__":
    _define_flags()
    command_line.run(main)
