"""Benchmarks: `python -m experiments.benchmark [--suite=model|renderer|pipeline|demon|robot]`.

    python -m experiments.benchmark                                        # the model
    python -m experiments.benchmark --torch_python=.torchref/bin/python    # + PyTorch
    python -m experiments.benchmark --torch_python=.torchref/bin/python --readme  # + README
    python -m experiments.benchmark --formulations=fused,vmap --repeats=3
    python -m experiments.benchmark --suite=pipeline                       # other suites
    python -m experiments.benchmark --suite=robot      # flow + depth + scale per pair
    python -m experiments.benchmark --torch_python=python3 --torch_device=cuda  # on a GPU
    python -m experiments.benchmark --readme_from=gpu.json    # README table from a result

The default suite (`experiments/benchmarks/model.py`) times the depth networks per
`apply_filter_banks` formulation: compile time, forward latency at batch 1 (median,
p90), forward throughput, the Adam train step, peak host memory and achieved
GFLOP/s, and the machine's float32 GEMM rate; with `--torch_python` the PyTorch
reference runs in the same session, alternating with the default formulation
(`--pairs`), and each pair's ratios are printed. `--readme` rewrites the README's speed
table from the result (`--readme_from` from a stored one: a GPU machine's result is
written into the README's GPU table where the README is edited). On a GPU,
`--torch_device=cuda` times the reference there, the device synchronised around each
call. The other suites are modules `experiments/benchmarks/<suite>.py`
with a `run() -> dict`, called with their defaults (run them directly for their own
flags). Every suite prints its result and writes it as JSON to `--output`.
"""

from __future__ import annotations

import importlib
import json
import time
from pathlib import Path

from absl import app, flags

from experiments import common

FLAGS = flags.FLAGS

flags.DEFINE_string("suite", "model", "Benchmark suite: model, renderer, pipeline, demon or robot.")
flags.DEFINE_string("output", "benchmark.json", "Where the JSON result is written.")
flags.DEFINE_list("models", ["global_local"], "Models of gld.models.registry.MODELS to time.")
flags.DEFINE_list("formulations", None, "apply_filter_banks formulations to time (default: all).")
flags.DEFINE_integer("height", 192, "Image height.")
flags.DEFINE_integer("width", 256, "Image width.")
flags.DEFINE_list("forward_batch_sizes", ["16", "64"], "Batch sizes of forward throughput.")
flags.DEFINE_integer("train_batch_size", 16, "Batch size of the train step.")
flags.DEFINE_integer("latency_repeats", 20, "Timed forward calls at batch 1.")
flags.DEFINE_integer("repeats", 5, "Timed calls of the other measurements.")
flags.DEFINE_float("max_seconds", 60.0, "A measurement stops after this many seconds of calls.")
flags.DEFINE_string(
    "torch_python", None, "Python with torch for the PyTorch reference (e.g. .torchref/bin/python)."
)
flags.DEFINE_string(
    "torch_reference", None, "torch_reference.py (default: ../shared/bench/torch_reference.py)."
)
flags.DEFINE_integer(
    "pairs", 3, "Alternating (PyTorch reference, default formulation) measurements.", lower_bound=1
)
flags.DEFINE_integer(
    "cpu_devices", 2, "CPU devices gld splits the host into, as the launchers do.", lower_bound=1
)
flags.DEFINE_bool(
    "readme", False, "Rewrite the README's speed table (between its markers) from the result."
)
flags.DEFINE_bool("torch_compile", True, "Also measure torch.compile in the reference.")
flags.DEFINE_enum(
    "torch_device", "cpu", ["cpu", "cuda"], "Where the PyTorch reference runs (cuda: a GPU's)."
)
flags.DEFINE_string(
    "readme_from",
    None,
    "Measure nothing: rewrite the README's speed table (the CPU's or the GPU's, as the "
    "result's backend says) from this stored model-suite result (--output's JSON).",
)
flags.DEFINE_bool(
    "quick", False, "Tiny shapes and one repeat: checks that everything runs, times nothing."
)

SUITES = ("model", "renderer", "pipeline", "demon", "robot")
# The README whose speed tables `--readme` and `--readme_from` rewrite.
README = Path(__file__).resolve().parents[1] / "README.md"


def run_model_suite() -> dict:
    from experiments.benchmarks import model, model_tables

    settings = dict(
        models=FLAGS.models,
        formulations=FLAGS.formulations,
        height=FLAGS.height,
        width=FLAGS.width,
        forward_batch_sizes=[int(b) for b in FLAGS.forward_batch_sizes],
        train_batch_size=FLAGS.train_batch_size,
        latency_repeats=FLAGS.latency_repeats,
        repeats=FLAGS.repeats,
        max_seconds=FLAGS.max_seconds,
        torch_python=FLAGS.torch_python,
        pairs=FLAGS.pairs,
        cpu_devices=FLAGS.cpu_devices,
        torch_compile=FLAGS.torch_compile,
        torch_device=FLAGS.torch_device,
    )
    if FLAGS.torch_reference:
        settings["torch_reference"] = FLAGS.torch_reference
    if FLAGS.quick:
        settings.update(
            height=16,
            width=24,
            forward_batch_sizes=[2],
            train_batch_size=2,
            latency_repeats=1,
            repeats=1,
        )
    result = model.run(**settings)
    print(model_tables.format_table(result))
    if FLAGS.readme:
        commit = common.commit_stamp(README) or "unknown"
        backend = model_tables.rewrite_readme(README, result, commit)
        print(f"rewrote the {backend.upper()} speed table of {README}")
    return result


def readme_from(path: Path) -> None:
    """`--readme_from`: the README's table from a stored result, at its recorded commit."""
    from experiments.benchmarks import model_tables

    try:
        backend = model_tables.readme_from(README, path)
    except ValueError as error:
        raise app.UsageError(f"--readme_from: {error}") from None
    print(f"rewrote the {backend.upper()} speed table of {README} from {path}")


def main(argv: list[str]) -> None:
    if len(argv) > 1:
        raise app.UsageError(f"unexpected arguments: {argv[1:]}")
    if FLAGS.suite not in SUITES:
        raise app.UsageError(f"--suite must be one of {SUITES}, got {FLAGS.suite!r}")
    if FLAGS.readme_from:
        readme_from(Path(FLAGS.readme_from))
        return
    start = time.time()
    if FLAGS.suite == "model":
        result = run_model_suite()
    else:
        module = importlib.import_module(f"experiments.benchmarks.{FLAGS.suite}")
        result = module.run()
        print(json.dumps(result, indent=1, default=str))
    output = Path(FLAGS.output)
    output.parent.mkdir(parents=True, exist_ok=True)
    record = {
        "suite": FLAGS.suite,
        "commit": common.commit_stamp(README),
        "seconds": time.time() - start,
        "result": result,
    }
    output.write_text(json.dumps(record, indent=1, default=str))
    print(f"wrote {output}")


if __name__ == "__main__":
    common.run(main)
