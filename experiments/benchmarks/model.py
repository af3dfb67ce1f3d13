"""Speed of the depth networks, per `apply_filter_banks` formulation, against PyTorch.

    python -m experiments.benchmark                                   # this suite
    python -m experiments.benchmark --torch_python=.torchref/bin/python

For every model of `gld.models.registry.MODELS` asked for (the global-local model once per
formulation of `gld.models.filter_banks.FORMULATIONS`) it measures, each in a fresh process so
that peak memory is the row's own: compile time of the train step, forward latency
at batch 1 (median and p90), forward throughput at the forward batch sizes, the time
of a whole Adam train step (the model's loss, `gld.training.trainer.make_train_step`), peak host
memory, and the GFLOP/s achieved (the flops of the computation, from XLA's cost
analysis of the "vmap" reference program, divided by the median time). With a
PyTorch interpreter it also runs `../shared/bench/torch_reference.py` (the same
network in PyTorch, eager and compiled) before and after, and reports ratios against
the goals: train step at most 0.8x PyTorch eager, forward at batch 16 no slower than
compiled PyTorch, forward at batch 1 no slower than PyTorch eager. Compare ratios
measured in one run only; on a shared machine absolute times drift.
"""

from __future__ import annotations

import json
import os
import resource
import statistics
import subprocess
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

REPO_ROOT = Path(__file__).resolve().parents[2]
DEFAULT_TORCH_REFERENCE = REPO_ROOT.parent / "shared" / "bench" / "torch_reference.py"
# The reference's fixed problem: 256x192 images, batch 1 and 16.
TORCH_SHAPE = (192, 256)


def _timed(fn: Callable[[], Any], repeats: int, max_seconds: float) -> list[float]:
    """Seconds per call of `fn` (after one warm-up), at least one call, at most `repeats`
    calls or `max_seconds` of calls."""
    fn()
    times: list[float] = []
    budget_start = time.perf_counter()
    while len(times) < repeats and (not times or time.perf_counter() - budget_start < max_seconds):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return times


def _flops(lowered) -> float | None:
    """Flops of a lowered XLA program from its cost analysis (None if unavailable)."""
    try:
        analysis = lowered.cost_analysis()
    except Exception:  # noqa: BLE001 - some backends do not implement it
        return None
    if isinstance(analysis, list | tuple):
        analysis = analysis[0] if analysis else None
    if not analysis or "flops" not in analysis:
        return None
    return float(analysis["flops"])


def _percentile(values: Sequence[float], fraction: float) -> float:
    ordered = sorted(values)
    return ordered[min(len(ordered) - 1, round(fraction * (len(ordered) - 1)))]


def measure_one(
    *,
    model_name: str,
    formulation: str | None,
    height: int,
    width: int,
    forward_batch_sizes: Sequence[int],
    train_batch_size: int,
    latency_repeats: int,
    repeats: int,
    max_seconds: float,
) -> dict[str, Any]:
    """Measures one (model, formulation) in this process. Times are seconds."""
    import jax
    import jax.numpy as jnp
    import numpy as np

    from gld.losses import supervised as losses
    from gld.models import registry
    from gld.runs import state as state_lib
    from gld.runs.optimizer import make_optimizer
    from gld.training import trainer as train_lib

    config = {"filter_formulation": formulation} if formulation is not None else {}
    model = registry.make_model(model_name, **config)
    # The flops of the computation itself, the same for every formulation: XLA's cost
    # analysis counts a loop body once, so lax.map formulations would be undercounted;
    # the vmap reference has no loop (its lowering is analysed, never compiled).
    flops_model = (
        registry.make_model(model_name, filter_formulation="vmap")
        if formulation is not None
        else model
    )
    rng = np.random.default_rng(0)

    def make_batch(batch_size: int) -> dict[str, jax.Array]:
        shape = (batch_size, height, width)
        sparse_mask = np.zeros(shape, bool)
        sparse_mask[:, height // 2, width // 2] = True
        return {
            "image1": jnp.asarray(rng.uniform(-0.5, 0.5, (*shape, 3)), jnp.float32),
            "image2": jnp.asarray(rng.uniform(-0.5, 0.5, (*shape, 3)), jnp.float32),
            "flow": jnp.asarray(rng.normal(0.0, 2.0, (*shape, 2)), jnp.float32),
            "depth": jnp.asarray(rng.uniform(1.0, 10.0, shape), jnp.float32),
            "sparse_mask": jnp.asarray(sparse_mask),
        }

    optimizer = make_optimizer(1e-4)
    state = state_lib.create_train_state(model, optimizer, height, width, seed=0)
    params = state.params
    # Every collection (batch-norm statistics too), with the parameters swapped in.
    extra_collections = {k: v for k, v in state.variables().items() if k != "params"}

    def make_forward(model):
        return lambda params, image1, image2, flow: model.apply(
            {"params": params, **extra_collections}, image1, image2, flow
        )["inv_depth"]

    result: dict[str, Any] = {
        "model": model_name,
        "formulation": formulation or "-",
        "backend": jax.default_backend(),
        "height": height,
        "width": width,
        "params": int(sum(x.size for x in jax.tree_util.tree_leaves(params))),
    }
    forward_jit = jax.jit(make_forward(model))
    flops_forward_jit = jax.jit(make_forward(flops_model))
    for batch_size in sorted({1, *forward_batch_sizes}):
        batch = make_batch(batch_size)
        args = (params, batch["image1"], batch["image2"], batch["flow"])
        start = time.perf_counter()
        compiled = forward_jit.lower(*args).compile()
        compile_s = time.perf_counter() - start
        run = lambda compiled=compiled, args=args: jax.block_until_ready(compiled(*args))
        count = latency_repeats if batch_size == 1 else repeats
        times = _timed(run, count, max_seconds)
        median = statistics.median(times)
        flops = _flops(flops_forward_jit.lower(*args))
        result[f"forward_b{batch_size}"] = {
            "compile_s": compile_s,
            "median_s": median,
            "p90_s": _percentile(times, 0.9),
            "pairs_per_s": batch_size / median,
            "gflop": flops / 1e9 if flops else None,
            "gflops_per_s": flops / median / 1e9 if flops else None,
            "repeats": len(times),
        }
        del batch, args, compiled

    def make_step(model):
        return train_lib.make_train_step(
            model=model, optimizer=optimizer, loss_weights=losses.LossWeights()
        )

    step_jit = jax.jit(make_step(model), donate_argnums=0)
    batch = {
        key: value
        for key, value in make_batch(train_batch_size).items()
        if key in train_lib.TRAIN_KEYS
    }
    step_rng = jax.random.key_data(jax.random.key(1))
    flops = _flops(jax.jit(make_step(flops_model)).lower(state, batch, step_rng))
    start = time.perf_counter()
    compiled_step = step_jit.lower(state, batch, step_rng).compile()
    compile_s = time.perf_counter() - start
    holder = {"state": state}

    def run_step() -> None:
        holder["state"], step_metrics = compiled_step(holder["state"], batch, step_rng)
        jax.block_until_ready(step_metrics)

    times = _timed(run_step, repeats, max_seconds)
    median = statistics.median(times)
    result[f"train_b{train_batch_size}"] = {
        "compile_s": compile_s,
        "median_s": median,
        "p90_s": _percentile(times, 0.9),
        "gflop": flops / 1e9 if flops else None,
        "gflops_per_s": flops / median / 1e9 if flops else None,
        "repeats": len(times),
    }
    # ru_maxrss is in KiB on Linux.
    result["peak_rss_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    return result


def _measure_in_subprocess(arguments: dict[str, Any]) -> dict[str, Any]:
    """Runs `measure_one` in a fresh interpreter (own compile cache, own peak memory)."""
    command = [sys.executable, "-m", "experiments.benchmarks.model", json.dumps(arguments)]
    completed = subprocess.run(
        command, cwd=REPO_ROOT, capture_output=True, text=True, env=dict(os.environ)
    )
    if completed.returncode != 0:
        return {
            "model": arguments["model_name"],
            "formulation": arguments["formulation"] or "-",
            "error": completed.stderr.strip().splitlines()[-1:] or ["exit status nonzero"],
        }
    return json.loads(completed.stdout.strip().splitlines()[-1])


def run_torch_reference(
    torch_python: str, reference: str | Path, repeats: int, compile_torch: bool
) -> dict[str, Any]:
    """Runs the PyTorch reference; returns its JSON (milliseconds) or {'error': ...}."""
    command = [torch_python, str(reference), "--repeats", str(repeats)]
    if not compile_torch:
        command.append("--no-compile")
    completed = subprocess.run(command, capture_output=True, text=True)
    if completed.returncode != 0:
        return {"error": (completed.stderr.strip().splitlines() or ["failed"])[-1]}
    return json.loads(completed.stdout.strip().splitlines()[-1])


def _torch_summary(rounds: list[dict[str, Any]]) -> dict[str, dict[str, float]]:
    """Median over rounds of each reference figure, in seconds: {mode: {key: s}}."""
    summary: dict[str, dict[str, float]] = {}
    for mode in ("eager", "compiled"):
        figures = [r[mode] for r in rounds if mode in r]
        if figures:
            summary[mode] = {
                key.replace("_ms", "_s"): statistics.median(f[key] for f in figures) / 1000
                for key in figures[0]
            }
    return summary


def goal_ratios(row: dict[str, Any], torch: dict[str, dict[str, float]]) -> dict[str, float]:
    """Ratios of gld's time to PyTorch's for the three goals (goal: <= 0.8, 1, 1)."""
    ratios = {}
    eager, compiled = torch.get("eager", {}), torch.get("compiled", {})
    if "train_b16" in row and "train_b16_s" in eager:
        ratios["train_b16_vs_eager (goal <= 0.8)"] = (
            row["train_b16"]["median_s"] / eager["train_b16_s"]
        )
    if "forward_b16" in row and "forward_b16_s" in compiled:
        ratios["forward_b16_vs_compiled (goal <= 1)"] = (
            row["forward_b16"]["median_s"] / compiled["forward_b16_s"]
        )
    if "forward_b1" in row and "forward_b1_s" in eager:
        ratios["forward_b1_vs_eager (goal <= 1)"] = (
            row["forward_b1"]["median_s"] / eager["forward_b1_s"]
        )
    return ratios


def run(
    *,
    models: Sequence[str] = ("global_local",),
    formulations: Sequence[str] | None = None,
    height: int = 192,
    width: int = 256,
    forward_batch_sizes: Sequence[int] = (16, 64),
    train_batch_size: int = 16,
    latency_repeats: int = 20,
    repeats: int = 5,
    max_seconds: float = 60.0,
    torch_python: str | None = None,
    torch_reference: str | Path = DEFAULT_TORCH_REFERENCE,
    torch_rounds: int = 2,
    torch_compile: bool = True,
    log: Callable[[str], None] = print,
) -> dict[str, Any]:
    """Measures every (model, formulation) and, optionally, the PyTorch reference.

    Args:
      models: names in `gld.models.registry.MODELS`; only "global_local" has formulations.
      formulations: keys of `gld.models.filter_banks.FORMULATIONS` (None = all).
      height, width: image size.
      forward_batch_sizes: batch sizes of the throughput measurements (batch 1 is
        always measured, for latency).
      train_batch_size: batch size of the train step.
      latency_repeats, repeats: timed calls at batch 1 and at the other sizes.
      max_seconds: a measurement stops after this many seconds of calls (slow rows).
      torch_python: a Python with torch to run the reference with (None = skip).
      torch_reference: path of torch_reference.py.
      torch_rounds: reference runs, split before and after gld's rows (median taken).
      torch_compile: also measure torch.compile.
      log: progress lines go here.

    Returns:
      {"rows": [...], "torch": {...}, "default_formulation": ..., "settings": {...}}.
    """
    from gld.models import filter_banks

    names = list(filter_banks.FORMULATIONS) if formulations is None else list(formulations)
    unknown = sorted(set(names) - set(filter_banks.FORMULATIONS))
    if unknown:
        raise ValueError(
            f"unknown formulations {unknown}; valid: {sorted(filter_banks.FORMULATIONS)}"
        )
    if torch_python is not None and not Path(torch_reference).is_file():
        raise FileNotFoundError(f"PyTorch reference not found: {torch_reference}")

    torch_rounds_results: list[dict[str, Any]] = []

    def torch_round() -> None:
        log(f"PyTorch reference ({torch_python}) ...")
        torch_rounds_results.append(
            run_torch_reference(torch_python, torch_reference, repeats, torch_compile)
        )
        log(f"  {json.dumps(torch_rounds_results[-1])}")

    if torch_python is not None and torch_rounds > 0:
        torch_round()
    rows = []
    for model_name in models:
        for formulation in names if model_name == "global_local" else [None]:
            log(f"{model_name} / {formulation or '-'} ...")
            row = _measure_in_subprocess(
                dict(
                    model_name=model_name,
                    formulation=formulation,
                    height=height,
                    width=width,
                    forward_batch_sizes=list(forward_batch_sizes),
                    train_batch_size=train_batch_size,
                    latency_repeats=latency_repeats,
                    repeats=repeats,
                    max_seconds=max_seconds,
                )
            )
            rows.append(row)
            log(f"  {format_row(row, train_batch_size, forward_batch_sizes)}")
    if torch_python is not None:
        for _ in range(torch_rounds - 1):
            torch_round()

    torch_summary = _torch_summary([r for r in torch_rounds_results if "error" not in r])
    comparable = (height, width) == TORCH_SHAPE and train_batch_size == 16
    if torch_summary and comparable:
        for row in rows:
            row["vs_torch"] = goal_ratios(row, torch_summary)
    return {
        "rows": rows,
        "torch": {"rounds": torch_rounds_results, "median_s": torch_summary},
        "default_formulation": {
            backend: filter_banks.default_formulation(backend) for backend in ("cpu", "gpu")
        },
        "settings": dict(
            height=height,
            width=width,
            forward_batch_sizes=list(forward_batch_sizes),
            train_batch_size=train_batch_size,
            latency_repeats=latency_repeats,
            repeats=repeats,
            max_seconds=max_seconds,
            torch_comparable=comparable,
            cpu_count=os.cpu_count(),
            load_average=os.getloadavg(),
        ),
    }


def format_row(
    row: dict[str, Any], train_batch_size: int, forward_batch_sizes: Sequence[int]
) -> str:
    """One line of the table for a measured row."""
    name = f"{row['model']}/{row['formulation']}"
    if "error" in row:
        return f"{name:28s} ERROR {row['error']}"
    forward_one = row["forward_b1"]
    train = row[f"train_b{train_batch_size}"]
    cells = [
        f"{name:28s}",
        f"{train['compile_s']:8.1f}",
        f"{forward_one['median_s'] * 1e3:8.1f}",
        f"{forward_one['p90_s'] * 1e3:8.1f}",
    ]
    cells += [f"{row[f'forward_b{b}']['pairs_per_s']:9.1f}" for b in forward_batch_sizes]
    cells += [f"{train['median_s']:8.3f}", f"{row['peak_rss_mb']:8.0f}"]
    for figure in (row[f"forward_b{max(forward_batch_sizes, default=1)}"], train):
        cells.append(f"{figure['gflops_per_s']:7.1f}" if figure["gflops_per_s"] else "      -")
    return " ".join(cells)


def format_table(result: dict[str, Any]) -> str:
    """The printed table: one line per row, then the reference and goal ratios."""
    settings = result["settings"]
    sizes = settings["forward_batch_sizes"]
    train_batch = settings["train_batch_size"]
    biggest = max(sizes, default=1)
    header = [
        f"{'model/formulation':28s}",
        f"{'compile':>8s}",
        f"{'b1 med':>8s}",
        f"{'b1 p90':>8s}",
    ]
    header += [f"{f'b{b} pr/s':>9s}" for b in sizes]
    header += [f"{f'train{train_batch}':>8s}", f"{'peak MB':>8s}"]
    header += [f"{f'GF/s{biggest}':>7s}", f"{'GF/s tr':>7s}"]
    lines = [
        f"{settings['height']}x{settings['width']}; compile = train step [s]; b1 = forward "
        f"latency [ms]; pr/s = forward pairs/s; train = Adam step [s]; GF/s = cost-analysis "
        "flops / median time",
        " ".join(header),
    ]
    lines += [format_row(row, train_batch, sizes) for row in result["rows"]]
    torch = result["torch"]["median_s"]
    for mode, figures in torch.items():
        lines.append(
            f"{'torch ' + mode:28s} b1 {figures['forward_b1_s'] * 1e3:.1f} ms, "
            f"b16 {16 / figures['forward_b16_s']:.1f} pairs/s, "
            f"train16 {figures['train_b16_s']:.3f} s"
        )
    for row in result["rows"]:
        if row.get("vs_torch"):
            ratios = ", ".join(f"{k} {v:.2f}" for k, v in row["vs_torch"].items())
            lines.append(f"{row['model']}/{row['formulation']}: {ratios}")
    lines.append(f"default formulation: {result['default_formulation']}")
    return "\n".join(lines)


if __name__ == "__main__":
    # Worker mode: one measurement, its JSON on the last stdout line.
    print(json.dumps(measure_one(**json.loads(sys.argv[1]))))
