"""Build throughput of the DeMoN builder (pairs/s at 256x192, DIS flow included).

    python -m experiments.benchmarks.demon                      # 30 pairs from 640x480 views
    python -m experiments.benchmarks.demon --num_pairs=10 --source_height=192 --source_width=256

A DeMoN-format file is written first from gld_scenes renders (640x480 like SUN3D
and RGB-D SLAM, lossy WebP like DeMoN's files, one scene group per pair as in the
test files), then timed: the per-pair work of the builder (decode WebP and LZ4,
resize to 256x192, relative pose, DIS flow, ground-truth flow, record encoding) and
a full `data.prepare("demon/custom")` build (TFDS writing and shuffling included).
Figures are wall-clock rates and, because the machine may be shared, CPU-time rates
of this process.
"""

from __future__ import annotations

import shutil
import tempfile
import time
from pathlib import Path
from typing import Any

import h5py
import numpy as np
from absl import flags

import data
from data import command_line
from data.demon import pairs, reader, writer
from data.gld_scenes import renderer, scenes
from experiments.benchmarks import format_table
from gld import geometry, records

FLAGS = flags.FLAGS


def write_synthetic_file(
    path: Path, num_pairs: int, height: int, width: int, webp_quality: int = 90
) -> None:
    """A DeMoN-format file of `num_pairs` rendered two-view scene groups.

    View 1 defines the world frame (R = I, t = 0); view 2 has the rendered relative pose.
    """
    settings = scenes.SceneSettings(height=height, width=width)
    with h5py.File(path, "w") as h5_file:
        for index in range(num_pairs):
            example = renderer.render_pair(renderer.example_rng(0, "demon_bench", index), settings)
            t0 = h5_file.create_group(f"scene_{index:04d}/frames/t0")
            t0.attrs["viewpoint_pairs"] = np.array([0, 1], np.int32)
            poses = (
                (np.eye(3), np.zeros(3)),
                (example["rotation"].astype(np.float64), example["translation"].astype(np.float64)),
            )
            for view, (rotation, translation) in enumerate(poses):
                intrinsics = example[f"intrinsics{view + 1}"].astype(np.float64)
                camera_matrix = geometry.intrinsics_matrix(intrinsics, height, width)
                writer.write_view(
                    t0.create_group(f"v{view}"),
                    example[f"image{view + 1}"],
                    example[f"depth{view + 1}"],
                    writer.demon_camera(camera_matrix, rotation, translation),
                    "camera_z",
                    webp_quality,
                )


def _stage_times(path: Path) -> dict[str, float]:
    """CPU milliseconds per pair of each builder stage, measured separately."""
    cpu: dict[str, float] = {"decode": 0.0, "resize": 0.0, "example": 0.0, "encode": 0.0}
    count = 0
    with reader.DemonFile(path) as demon_file:
        for group in demon_file.groups():
            start = time.process_time()
            views = [demon_file.view(group, index) for index in (0, 1)]
            cpu["decode"] += time.process_time() - start
            start = time.process_time()
            views = [pairs.resize_view(view) for view in views]
            cpu["resize"] += time.process_time() - start
            start = time.process_time()
            example = pairs.make_example(*views, group)
            cpu["example"] += time.process_time() - start
            start = time.process_time()
            records.encode(example)
            cpu["encode"] += time.process_time() - start
            count += 1
    return {f"{stage}_ms_per_pair": 1000 * value / count for stage, value in cpu.items()}


def run(
    *,
    num_pairs: int = 30,
    source_height: int = 480,
    source_width: int = 640,
    full_build: bool = True,
    work_dir: str | None = None,
) -> dict[str, Any]:
    """Measures the DeMoN build on a synthetic file.

    Args:
      num_pairs: scene groups (one pair each) in the file.
      source_height, source_width: resolution of the stored views (resized to 256x192).
      full_build: also time `data.prepare("demon/custom")` end to end.
      work_dir: where the file and the build go (default: a temporary directory, removed).

    Returns:
      A flat dict: `pairs_per_s` / `pairs_per_cpu_s` of the builder's per-pair work,
      the CPU milliseconds of each stage, `file_mb`, and for the full build
      `build_pairs_per_s`.
    """
    root = Path(work_dir) if work_dir else Path(tempfile.mkdtemp(prefix="demon_bench"))
    manual_dir = root / "manual"
    manual_dir.mkdir(parents=True, exist_ok=True)
    path = manual_dir / "custom_test.h5"
    results: dict[str, Any] = {
        "num_pairs": num_pairs,
        "source_size": f"{source_width}x{source_height}",
        "output_size": f"{pairs.WIDTH}x{pairs.HEIGHT}",
    }
    try:
        write_synthetic_file(path, num_pairs, source_height, source_width)
        results["file_mb"] = path.stat().st_size / 2**20
        list(pairs.generate([path], "test"))  # warm-up: imports, OpenCV, page cache
        wall, cpu = time.perf_counter(), time.process_time()
        for _, example in pairs.generate([path], "test"):
            records.encode(example)
        wall, cpu = time.perf_counter() - wall, time.process_time() - cpu
        results["pairs_per_s"] = num_pairs / wall
        results["pairs_per_cpu_s"] = num_pairs / cpu
        results.update(_stage_times(path))
        if full_build:
            wall = time.perf_counter()
            builder = data.prepare("demon/custom", root / "datasets", manual_dir)
            results["build_s"] = time.perf_counter() - wall
            results["build_pairs"] = builder.info.splits["test"].num_examples
            results["build_pairs_per_s"] = results["build_pairs"] / results["build_s"]
    finally:
        if not work_dir:
            shutil.rmtree(root, ignore_errors=True)
    return results


def _define_flags() -> None:
    # Defined only when run as a script, so importing `run` defines no global flags.
    flags.DEFINE_integer("num_pairs", 30, "Pairs (scene groups) in the synthetic file.")
    flags.DEFINE_integer("source_height", 480, "Height of the stored views.")
    flags.DEFINE_integer("source_width", 640, "Width of the stored views.")
    flags.DEFINE_bool("full_build", True, "Also time data.prepare('demon/custom').")
    flags.DEFINE_string("work_dir", None, "Where to write (default: a temporary directory).")


def main(argv: list[str]) -> None:
    del argv
    results = run(
        num_pairs=FLAGS.num_pairs,
        source_height=FLAGS.source_height,
        source_width=FLAGS.source_width,
        full_build=FLAGS.full_build,
        work_dir=FLAGS.work_dir,
    )
    print(format_table(results))


if __name__ == "__main__":
    _define_flags()
    command_line.run(main)
