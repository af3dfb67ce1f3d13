"""Speed of the depth networks, per `apply_filter_banks` formulation, against PyTorch.

    python -m experiments.benchmark                                   # this suite
    python -m experiments.benchmark --torch_python=.torchref/bin/python --readme

For every model of `gld.models.registry.MODELS` asked for (the global-local model once per
formulation of `gld.models.filter_banks.FORMULATIONS`) it measures, each in a fresh process so
that peak memory is the row's own: compile time of the train step, forward latency
at batch 1 (median and p90), forward throughput at the forward batch sizes, the time
of a whole Adam train step (the model's loss, `gld.training.trainer.make_train_step`,
compiled as the trainer compiles it: over a mesh of `cpu_devices` CPU devices), peak
host memory, and the GFLOP/s achieved (the flops of the computation, from XLA's cost
analysis of the "vmap" reference program, divided by the median time). It also
measures the machine's float32 GEMM rate (a 2048x2048 matmul through XLA, all cores;
8192x8192 on an accelerator), the peak the train step's GFLOP/s is compared with.

With a PyTorch interpreter it runs the PyTorch reference (`torch_pairs`) alternating with
the measured backend's default formulation's row, `pairs` times: each pair's ratios are
reported, with their median and spread, and
the reference is called noisy when its own train step varies by more than 25% across
pairs. Goals: train step at most 0.5x PyTorch eager and below compiled PyTorch; forward
at batch 16 no slower than compiled PyTorch; forward at batch 1 no slower than eager.
`markdown_table` writes the README's speed table from a result (`--readme`).
"""

from __future__ import annotations

import datetime
import json
import os
import platform
import resource
import statistics
import subprocess
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from experiments.benchmarks.model_tables import format_row
from experiments.benchmarks.torch_pairs import (
    DEFAULT_TORCH_REFERENCE,
    TORCH_SHAPE,
    goal_ratios,
    run_torch_reference,
    summarise_pairs,
    torch_summary,
)

REPO_ROOT = Path(__file__).resolve().parents[2]


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


def _flops(jitted, *args) -> float | None:
    """Flops of `jitted(*args)` from XLA's cost analysis of its program lowered for the
    CPU, whatever the backend: the count belongs to the program, and a GPU analyses
    only its compiled program, where cuDNN's convolutions count nothing. None if
    unavailable."""
    try:
        analysis = jitted.trace(*args).lower(lowering_platforms=("cpu",)).cost_analysis()
    except Exception:  # noqa: BLE001 - an analysis is a nicety, never a failure
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
    cpu_devices: int = 1,
) -> dict[str, Any]:
    """Measures one (model, formulation) in this process, on `cpu_devices` CPU devices
    (each batch split over as many as divide it, as the trainer does). Times are seconds."""
    from gld import sharding

    sharding.split_cpu_devices(cpu_devices)
    import jax
    import jax.numpy as jnp
    import numpy as np

    from gld.losses import supervised as losses
    from gld.models import registry
    from gld.runs import state as state_lib
    from gld.runs.optimizer import make_optimizer
    from gld.training import loop
    from gld.training import trainer as train_lib

    def mesh_for(batch_size: int):
        count = sharding.devices_for_batch(batch_size, len(jax.devices()))
        return sharding.make_mesh(jax.devices()[:count])

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
        "device_kind": jax.devices()[0].device_kind,
        "matmul_precision": jax.config.jax_default_matmul_precision or "default",
        "devices": len(jax.devices()),
        "height": height,
        "width": width,
        "params": int(sum(x.size for x in jax.tree_util.tree_leaves(params))),
    }
    flops_forward_jit = jax.jit(make_forward(flops_model))
    for batch_size in sorted({1, *forward_batch_sizes}):
        mesh = mesh_for(batch_size)
        batch = make_batch(batch_size)
        args = (params, batch["image1"], batch["image2"], batch["flow"])
        flops = _flops(flops_forward_jit, *args)
        args = (
            jax.device_put(params, sharding.replicated(mesh)),
            *jax.device_put(args[1:], sharding.batch_sharded(mesh)),
        )
        start = time.perf_counter()
        with jax.set_mesh(mesh):  # traced over the mesh, as the evaluation does
            compiled = jax.jit(make_forward(model)).lower(*args).compile()
        compile_s = time.perf_counter() - start
        run = lambda compiled=compiled, args=args: jax.block_until_ready(compiled(*args))
        count = latency_repeats if batch_size == 1 else repeats
        times = _timed(run, count, max_seconds)
        median = statistics.median(times)
        result[f"forward_b{batch_size}"] = {
            "compile_s": compile_s,
            "median_s": median,
            "p90_s": _percentile(times, 0.9),
            "pairs_per_s": batch_size / median,
            "gflop": flops / 1e9 if flops else None,
            "gflops_per_s": flops / median / 1e9 if flops else None,
            "repeats": len(times),
            "devices": mesh.devices.size,
        }
        del batch, args, compiled

    def make_step(model):
        return train_lib.make_train_step(
            model=model, optimizer=optimizer, loss_weights=losses.LossWeights()
        )

    batch = {
        key: value
        for key, value in make_batch(train_batch_size).items()
        if key in train_lib.TRAIN_KEYS
    }
    step_rng = jax.random.key_data(jax.random.key(1))
    flops = _flops(jax.jit(make_step(flops_model)), state, batch, step_rng)
    mesh = mesh_for(train_batch_size)
    # Compiled as the trainer compiles it (`loop.jit_train_step`).
    placement = sharding.state_sharding(state, mesh)
    step_jit = loop.jit_train_step(make_step(model), mesh, placement).__wrapped__
    state = jax.device_put(state, placement)
    batch = sharding.to_global_batch(batch, mesh, list(batch))
    start = time.perf_counter()
    with jax.set_mesh(mesh):
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
        "devices": mesh.devices.size,
    }
    # ru_maxrss is in KiB on Linux.
    result["peak_rss_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    # An accelerator's own peak (its allocator's; None on the CPU).
    stats = jax.devices()[0].memory_stats() or {}
    if "peak_bytes_in_use" in stats:
        result["peak_device_mb"] = stats["peak_bytes_in_use"] / 2**20
    return result


def measure_gemm(size: int | None = None, repeats: int = 10) -> dict[str, Any]:
    """The machine's float32 GEMM rate through XLA at JAX's default precision (all
    cores, one device): a `size` x `size` matmul (None: 2048 on the CPU, 8192 on an
    accelerator, large enough to fill it),
    best and median GFLOP/s over `repeats` calls, with the backend and its device."""
    import jax
    import jax.numpy as jnp

    backend = jax.default_backend()
    size = size or (2048 if backend == "cpu" else 8192)
    matrix = jax.random.normal(jax.random.key(0), (size, size), jnp.float32)
    matmul = jax.jit(lambda a: a @ a)
    times = _timed(lambda: jax.block_until_ready(matmul(matrix)), repeats, 60.0)
    flop = 2.0 * size**3
    return {
        "backend": backend,
        "device_kind": jax.devices()[0].device_kind,
        "size": size,
        "best_gflops_per_s": flop / min(times) / 1e9,
        "median_gflops_per_s": flop / statistics.median(times) / 1e9,
        "repeats": len(times),
    }


def _in_subprocess(kind: str, arguments: dict[str, Any]) -> dict[str, Any]:
    """`measure_one` ("row") or `measure_gemm` ("gemm") in a fresh interpreter (own
    compile cache, own peak memory, own CPU devices); {"error": ...} if it fails."""
    command = [sys.executable, "-m", "experiments.benchmarks.model", kind, json.dumps(arguments)]
    completed = subprocess.run(
        command, cwd=REPO_ROOT, capture_output=True, text=True, env=dict(os.environ)
    )
    if completed.returncode != 0:
        return {"error": completed.stderr.strip().splitlines()[-1:] or ["exit status nonzero"]}
    return json.loads(completed.stdout.strip().splitlines()[-1])


def _measure_in_subprocess(arguments: dict[str, Any]) -> dict[str, Any]:
    row = _in_subprocess("row", arguments)
    if "error" in row:
        row = {
            "model": arguments["model_name"],
            "formulation": arguments["formulation"] or "-",
            **row,
        }
    return row


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
    pairs: int = 3,
    torch_compile: bool = True,
    torch_device: str = "cpu",
    cpu_devices: int = 2,
    log: Callable[[str], None] = print,
) -> dict[str, Any]:
    """Measures the GEMM peak, the default formulation alternating with the PyTorch
    reference `pairs` times, then every other (model, formulation) once.

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
      pairs: alternating (reference, default formulation) measurements (>= 1).
      torch_compile: also measure torch.compile.
      torch_device: where the reference runs ("cpu", or "cuda" beside a JAX GPU).
      cpu_devices: CPU devices each gld measurement splits the host into, as the
        launchers do (`--cpu_devices`).
      log: progress lines go here.

    Returns:
      {"rows": [...], "pairs": [...], "summary": {...}, "gemm": {...}, "torch": {...},
       "default_formulation": ..., "paired_formulation": ..., "backend": ...,
       "settings": {...}}. The paired formulation is the measured backend's default.
    """
    from gld.models import filter_banks

    names = list(filter_banks.FORMULATIONS) if formulations is None else list(formulations)
    unknown = sorted(set(names) - set(filter_banks.FORMULATIONS))
    if unknown:
        raise ValueError(
            f"unknown formulations {unknown}; valid: {sorted(filter_banks.FORMULATIONS)}"
        )
    if pairs < 1:
        raise ValueError(f"pairs must be >= 1, got {pairs}")
    if torch_python is not None and not Path(torch_reference).is_file():
        raise FileNotFoundError(f"PyTorch reference not found: {torch_reference}")

    # The settings of every measurement (`measure_one`'s arguments but the row's own).
    measurement = dict(
        height=height,
        width=width,
        forward_batch_sizes=list(forward_batch_sizes),
        train_batch_size=train_batch_size,
        latency_repeats=latency_repeats,
        repeats=repeats,
        max_seconds=max_seconds,
        cpu_devices=cpu_devices,
    )

    def measure(model_name: str, formulation: str | None) -> dict[str, Any]:
        log(f"{model_name} / {formulation or '-'} ...")
        row = _measure_in_subprocess(
            dict(model_name=model_name, formulation=formulation, **measurement)
        )
        log(f"  {format_row(row, train_batch_size, forward_batch_sizes)}")
        return row

    log("float32 GEMM ...")
    gemm = _in_subprocess("gemm", {})
    log(f"  {json.dumps(gemm)}")
    # The backend as the measuring interpreters see it (this one never starts JAX, so
    # that an accelerator's memory is theirs alone).
    backend = gemm.get("backend", "cpu")
    default = filter_banks.default_formulation(backend)
    # The first model alternates with the reference: with the default formulation when
    # it is the global-local model (the others have no filter banks).
    paired_name = (
        (default if default in names else names[0]) if models[0] == "global_local" else None
    )
    measured_pairs = []
    for index in range(pairs):
        reference = None
        if torch_python is not None:
            log(f"PyTorch reference ({torch_python}), pair {index + 1} of {pairs} ...")
            reference = run_torch_reference(
                torch_python, torch_reference, repeats, torch_compile, torch_device
            )
            log(f"  {json.dumps(reference)}")
        measured_pairs.append({"torch": reference, "gld": measure(models[0], paired_name)})
    rows = [pair["gld"] for pair in measured_pairs]
    for model_name in models:
        for formulation in names if model_name == "global_local" else [None]:
            if (model_name, formulation) != (models[0], paired_name):
                rows.append(measure(model_name, formulation))

    references = [p["torch"] for p in measured_pairs if p["torch"] and "error" not in p["torch"]]
    reference_summary = torch_summary(references)
    comparable = (height, width) == TORCH_SHAPE and train_batch_size == 16
    if reference_summary and comparable:
        for row in rows:
            if "error" not in row:
                row["vs_torch"] = goal_ratios(row, reference_summary)
    summary = summarise_pairs(measured_pairs) if comparable else {}
    train = measured_pairs[-1]["gld"].get(f"train_b{train_batch_size}", {})
    if "error" not in gemm and train.get("gflops_per_s"):
        summary["train_share_of_gemm_peak"] = [
            p["gld"][f"train_b{train_batch_size}"]["gflops_per_s"] / gemm["best_gflops_per_s"]
            for p in measured_pairs
            if "error" not in p["gld"]
        ]
    return {
        "rows": rows,
        "pairs": measured_pairs,
        "summary": summary,
        "gemm": gemm,
        "torch": {
            "rounds": [p["torch"] for p in measured_pairs if p["torch"]],
            "median_s": reference_summary,
        },
        "default_formulation": {
            name: filter_banks.default_formulation(name) for name in ("cpu", "gpu")
        },
        "paired_formulation": paired_name,
        "backend": backend,
        "settings": dict(
            **measurement,
            pairs=pairs,
            torch_comparable=comparable,
            torch_device=torch_device,
            cpu_count=os.cpu_count(),
            load_average=os.getloadavg(),
        ),
        "machine": machine(gemm.get("device_kind") if backend != "cpu" else None),
        "date": datetime.datetime.now(datetime.UTC).strftime("%Y-%m-%d %H:%M UTC"),
    }


def machine(accelerator: str | None = None) -> str:
    """The CPU's model name and core count, as /proc/cpuinfo gives them, after the
    accelerator's name if one was measured."""
    name = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                name = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    host = f"{name}, {os.cpu_count()} cores"
    return f"{accelerator} (host: {host})" if accelerator else host


if __name__ == "__main__":
    # Worker mode: one measurement, its JSON on the last stdout line, with the freed
    # memory kept for reuse as the launchers keep it.
    from gld import host_memory

    host_memory.keep_freed_memory()
    worker = {"row": measure_one, "gemm": measure_gemm}[sys.argv[1]]
    print(json.dumps(worker(**json.loads(sys.argv[2]))))
