"""Latency of the whole robot loop, per image pair at batch 1: flow, depth, scale.

    python -m experiments.benchmark --suite=robot            # 256x192 and 128x96
    python -m experiments.benchmark --suite=robot --quick    # tiny images, one pair
    python -m experiments.benchmarks.robot --repeats=100     # this suite's own flags
    python -m experiments.benchmarks.robot --artifact=runs/robot/model.gldx   # your file

What a robot does for every new pair: estimate the flow (OpenCV DIS, `gld.flow`), run
the depth network, and turn its depth (in baselines) into metres with one range
reading (`gld.inference.metric_scale.scale_from_ranges`). Each stage and the whole loop
are timed per pair (median and p90), at the paper's resolution (256x192) and at the embedded
benchmark's (128x96, `gld_scenes/small`), with the network run two ways: jit-compiled
from the live Flax model, and as the file `python -m experiments.export` writes, loaded
by `gld.inference.deploy`. The "runtime" row times that file end to end as a robot runs
it, pair by pair between the other two: `gld.inference.runtime.DepthRuntime.predict`
from the two frames to metric depth (input checks, resizing, the flow the file records,
the network, scale, all inside);
`--artifact` times a given file so, at its resolution. The network is untrained (latency
does not depend on the weights) and the pair is rendered by the embedded benchmark's
renderer. The paper's figures (an
NVIDIA GeForce 940MX: 4 ms for the network, 45 ms for PWC-Net flow) are printed as the
reference row; they were measured on a GPU with another flow network.
"""

from __future__ import annotations

import os
import statistics
import tempfile
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from absl import app, flags

from data import command_line

FLAGS = flags.FLAGS

SIZES = ((192, 256), (96, 128))  # (height, width): the paper's, gld_scenes/small's
QUICK_SIZES = ((24, 32),)
STAGES = ("flow", "model", "scale", "total")
PAPER_REFERENCE = {
    "hardware": "NVIDIA GeForce 940MX (the paper)",
    "flow_method": "PWC-Net",
    "height": 192,
    "width": 256,
    "flow_ms": 45.0,
    "model_ms": 4.0,
    "total_ms": 49.0,
}


def _percentile(values: Sequence[float], fraction: float) -> float:
    ordered = sorted(values)
    return ordered[min(len(ordered) - 1, round(fraction * (len(ordered) - 1)))]


def _quick_requested() -> bool:
    """`--quick` of `python -m experiments.benchmark`, when that launcher parsed it."""
    return "quick" in FLAGS and FLAGS.is_parsed() and bool(FLAGS.quick)


def _range_reading(depth) -> tuple[list[float], float]:
    """The (u, v) pixel nearest the image centre with a valid true depth, and that depth:
    what a range sensor aligned with the optical axis measures."""
    import numpy as np

    height, width = depth.shape
    rows, columns = np.nonzero(np.isfinite(depth) & (depth > 0))
    if len(rows) == 0:
        raise ValueError("the rendered pair has no valid depth for a range reading")
    nearest = np.argmin((rows - (height - 1) / 2) ** 2 + (columns - (width - 1) / 2) ** 2)
    row, column = rows[nearest], columns[nearest]
    return [float(column), float(row)], float(depth[row, column])


def _summary(times_s: Sequence[float]) -> dict[str, float]:
    return {
        "median_ms": 1e3 * statistics.median(times_s),
        "p90_ms": 1e3 * _percentile(times_s, 0.9),
    }


def _networks(height: int, width: int, seed: int, scratch: Path, pair: dict) -> dict:
    """name -> (forward(image1, image2, flow) -> depth [H, W], set-up times, formulation)
    for the untrained global-local network, jit-compiled live and exported."""
    import jax
    import jax.numpy as jnp
    import numpy as np

    from gld import flow as flow_lib
    from gld.inference import deploy, export
    from gld.models import filter_banks, registry

    model = registry.make_model("global_local")
    # Weights drawn with numpy into the model's structure (std 1/sqrt(fan-in), biases 0):
    # latency does not depend on them, and compiling `model.init` would take seconds.
    shapes = jax.eval_shape(
        model.init,
        jax.random.key(seed),
        jax.ShapeDtypeStruct((1, height, width, 3), jnp.float32),
        jax.ShapeDtypeStruct((1, height, width, 3), jnp.float32),
        jax.ShapeDtypeStruct((1, height, width, 2), jnp.float32),
    )
    rng = np.random.default_rng(seed)

    def draw(leaf):
        if len(leaf.shape) < 2:
            return np.zeros(leaf.shape, leaf.dtype)
        fan_in = int(np.prod(leaf.shape[:-1]))
        return rng.normal(0.0, fan_in**-0.5, leaf.shape).astype(leaf.dtype)

    variables = jax.tree_util.tree_map(draw, shapes)

    @jax.jit
    def apply(variables, image1, image2, flow):
        outputs = model.apply(variables, image1, image2, flow)
        return {key: value for key, value in outputs.items() if isinstance(value, jax.Array)}

    def live(image1, image2, flow):
        # The same host work as gld.inference.deploy: uint8 -> [-0.5, 0.5], results to numpy.
        images = [image[None].astype(np.float32) / 255.0 - 0.5 for image in (image1, image2)]
        outputs = jax.device_get(apply(variables, *images, flow[None]))
        return np.asarray(outputs["depth"][0])

    image1, image2 = pair["image1"], pair["image2"]
    start = time.perf_counter()
    live(image1, image2, flow_lib.estimate(image1, image2))
    live_setup = {"compile_s": time.perf_counter() - start}

    path = scratch / f"robot_{height}x{width}.gldx"
    start = time.perf_counter()
    metadata = export.export_model(model, variables, path, height=height, width=width)
    exported_setup = {"export_s": time.perf_counter() - start}
    start = time.perf_counter()
    deployed = deploy.DeployedModel.load(path)
    deployed(image1, image2, flow_lib.estimate(image1, image2))
    exported_setup["load_s"] = time.perf_counter() - start
    return {
        "jit (live)": (live, live_setup, filter_banks.default_formulation()),
        "exported": (deployed, exported_setup, metadata["formulation"]),
    }


def _measurements(runtime, pair: dict) -> dict[str, Any]:
    """What the runtime is given besides the frames: one range reading, and the odometry
    or the camera where the model reads them (the camera only then: with it the runtime
    also lifts every pixel to 3-D, which the other rows do not)."""
    import numpy as np

    pixel, distance = _range_reading(pair["depth1"])
    given: dict[str, Any] = {"ranges": [[*pixel, distance]]}
    if runtime.needs_odometry:
        given.update(rotation=pair["rotation"], translation=pair["translation"])
    if runtime.needs_camera:
        height, width = pair["depth1"].shape
        scale = np.array([width, height, width, height], np.float64)
        fx, fy, cx, cy = np.asarray(pair["intrinsics1"], np.float64) * scale
        given["intrinsics"] = (fx, fy, cx - 0.5, cy - 0.5)
    return given


def _load_runtime(path: Path, pair: dict) -> tuple[Any, dict[str, Any], float]:
    """(`DepthRuntime` of the file, what it is given besides the frames, seconds to load
    it and make the first call)."""
    from gld.inference.runtime import DepthRuntime

    start = time.perf_counter()
    runtime = DepthRuntime.load(path)
    given = _measurements(runtime, pair)
    runtime.predict(pair["image1"], pair["image2"], **given)
    return runtime, given, time.perf_counter() - start


def _runtime_row(runtime, load_s: float, totals: list[float]) -> dict[str, Any]:
    """The end-to-end row of a file run by `DepthRuntime`: its total alone."""
    row = {"network": "runtime", "flow_estimator": runtime.flow["estimator"]}
    row.update({stage: None for stage in STAGES[:-1]})
    return {**row, "total": _summary(totals), "load_s": load_s}


def _time_loops(
    networks: dict, pair: dict, repeats: int, runtime: tuple | None = None
) -> dict[str, dict[str, list[float]]]:
    """Seconds of every stage of `repeats` robot loops per network, after a warm-up loop,
    and with `runtime` ((DepthRuntime, its measurements)) the seconds of its whole call
    under "runtime".

    The networks and the runtime alternate pair by pair, so that a shared machine's
    drifting load falls on all alike.
    """
    import numpy as np

    from gld import flow as flow_lib
    from gld.inference import metric_scale

    image1, image2 = pair["image1"], pair["image2"]
    pixel, distance = _range_reading(pair["depth1"])
    times = {name: {stage: [] for stage in STAGES} for name in networks}
    times["runtime"] = {"total": []}
    for index in range(repeats + 1):
        for name, (forward, _, _) in networks.items():
            start = time.perf_counter()
            flow = flow_lib.estimate(image1, image2)
            after_flow = time.perf_counter()
            depth = forward(image1, image2, flow)
            after_model = time.perf_counter()
            metres = metric_scale.scale_from_ranges(depth, [pixel], [distance]) * depth
            end = time.perf_counter()
            if not np.all(np.isfinite(metres)):
                raise ValueError(f"{name} gave a non-finite metric depth map")
            if index > 0:
                timed = times[name]
                timed["flow"].append(after_flow - start)
                timed["model"].append(after_model - after_flow)
                timed["scale"].append(end - after_model)
                timed["total"].append(end - start)
        if runtime is not None:
            model, given = runtime
            start = time.perf_counter()
            metres = model.predict(image1, image2, **given)["depth"]
            if index > 0:
                times["runtime"]["total"].append(time.perf_counter() - start)
            if not np.all(np.isfinite(metres)):
                raise ValueError("the runtime gave a non-finite metric depth map")
    return times


def run(
    *,
    sizes: Sequence[tuple[int, int]] = SIZES,
    repeats: int = 50,
    quick: bool | None = None,
    seed: int = 0,
    artifact: str | Path | None = None,
    log: Callable[[str], None] = print,
) -> dict[str, Any]:
    """Times flow + network + scale recovery per pair, the network live and exported,
    and the exported file end to end (`DepthRuntime`).

    Args:
      sizes: (height, width) image sizes.
      repeats: timed pairs per size and network (after one untimed warm-up loop each).
      quick: tiny images and one pair (checks that everything runs; times nothing);
        None follows `python -m experiments.benchmark --quick`.
      seed: seeds the rendered pair and the untrained weights.
      artifact: an exported file to time end to end alone, at its resolution (`sizes`
        is then ignored).
      log: progress lines and the table go here.

    Returns:
      {"rows": [{"height", "width", "network", "formulation", "flow"/"model"/"scale"/
       "total": {"median_ms", "p90_ms"}, "compile_s" (live) or "export_s" and "load_s"
       (exported, the load including the first call)}], "reference": PAPER_REFERENCE,
       "settings": {...}}.
    """
    if quick is None:
        quick = _quick_requested()
    if quick:
        sizes, repeats = QUICK_SIZES, 1
    if repeats < 1:
        raise ValueError(f"repeats must be >= 1, got {repeats}")
    import jax

    from data.gld_scenes import renderer, scenes
    from gld import flow as flow_lib

    rows = []
    if artifact is not None:
        from gld.inference.deploy import DeployedModel

        model = DeployedModel.load(artifact)
        sizes = [(model.height, model.width)]
        settings = scenes.SceneSettings(height=model.height, width=model.width)
        pair = renderer.render_pair(renderer.example_rng(seed, "robot", 0), settings)
        log(f"{artifact}: {model.metadata['model']} at {model.width}x{model.height}")
        runtime, given, load_s = _load_runtime(Path(artifact), pair)
        totals = _time_loops({}, pair, repeats, (runtime, given))["runtime"]["total"]
        row = _runtime_row(runtime, load_s, totals)
        rows.append({"height": model.height, "width": model.width, **row})
    with tempfile.TemporaryDirectory(prefix="gld_robot_benchmark") as scratch:
        for height, width in sizes if artifact is None else ():
            log(f"{width}x{height}: rendering a pair, compiling and exporting the network ...")
            settings = scenes.SceneSettings(height=height, width=width)
            pair = renderer.render_pair(renderer.example_rng(seed, "robot", 0), settings)
            networks = _networks(height, width, seed, Path(scratch), pair)
            path = Path(scratch) / f"robot_{height}x{width}.gldx"
            runtime, given, load_s = _load_runtime(path, pair)
            times = _time_loops(networks, pair, repeats, (runtime, given))
            for name, (_, setup, formulation) in networks.items():
                row = {"height": height, "width": width, "network": name}
                row["formulation"] = formulation
                row.update({stage: _summary(times[name][stage]) for stage in STAGES})
                row.update(setup)
                rows.append(row)
            row = _runtime_row(runtime, load_s, times["runtime"]["total"])
            rows.append({"height": height, "width": width, "formulation": formulation, **row})

    result = {
        "rows": rows,
        "reference": PAPER_REFERENCE,
        "settings": {
            "sizes": [list(size) for size in sizes],
            "repeats": repeats,
            "quick": quick,
            "batch_size": 1,
            "flow_method": f"{flow_lib.DEFAULT_ESTIMATOR} (OpenCV)",
            "artifact": None if artifact is None else str(artifact),
            "scale_method": "scale_from_ranges, one reading at the pixel nearest the centre",
            "backend": jax.default_backend(),
            "cpu_count": os.cpu_count(),
            "load_average": os.getloadavg(),
        },
    }
    log(format_table(result))
    return result


def format_row(row: dict[str, Any]) -> str:
    """One line: size, network, then median / p90 [ms] of every stage."""
    size = f"{row['width']}x{row['height']}"
    cells = [f"{size:8s}", f"{row['network']:12s}"]
    cells += [
        f"{'-':>7s}{'':8s}"
        if row[stage] is None
        else f"{row[stage]['median_ms']:7.1f} /{row[stage]['p90_ms']:6.1f}"
        for stage in STAGES
    ]
    return " ".join(cells)


def format_table(result: dict[str, Any]) -> str:
    """The printed table: a row per size and network, then the paper's reference."""
    settings = result["settings"]
    reference = result["reference"]
    lines = [
        f"robot loop per pair, batch 1, {settings['repeats']} pairs, {settings['backend']} "
        f"({settings['cpu_count']} cores, load {settings['load_average'][0]:.1f}); "
        "median / p90 [ms]",
        f"{'size':8s} {'network':12s} " + " ".join(f"{stage:>15s}" for stage in STAGES),
    ]
    lines += [format_row(row) for row in result["rows"]]
    size = f"{reference['width']}x{reference['height']}"
    figures = [reference["flow_ms"], reference["model_ms"], None, reference["total_ms"]]
    cells = [f"{size:8s}", f"{'paper':12s}"]
    cells += [f"{'-' if value is None else f'{value:.1f}':>7s}{'':8s}" for value in figures]
    lines.append(" ".join(cells) + f"({reference['hardware']}, {reference['flow_method']} flow)")
    for row in result["rows"]:
        if "compile_s" in row:
            setup = f"compile {row['compile_s']:.1f} s"
        elif "export_s" in row:
            setup = f"export {row['export_s']:.1f} s, load + first call {row['load_s']:.1f} s"
        else:
            setup = (
                f"frames to metric depth, {row['flow_estimator']} flow inside; load + first "
                f"call {row['load_s']:.1f} s"
            )
        size = f"{row['width']}x{row['height']}"
        formulation = row.get("formulation")
        described = "" if formulation is None else f" (formulation {formulation})"
        lines.append(f"{size} {row['network']}{described}: {setup}")
    return "\n".join(lines)


def _define_flags() -> None:
    # Defined only when run as a script, so importing `run` defines no global flags.
    flags.DEFINE_integer("repeats", 50, "Timed pairs per size and network.")
    flags.DEFINE_list("sizes", ["192x256", "96x128"], "Image sizes, HEIGHTxWIDTH.")
    flags.DEFINE_bool("quick", False, "Tiny images and one pair: checks that everything runs.")
    flags.DEFINE_string("output", None, "Also write the result as JSON here.")
    flags.DEFINE_string(
        "artifact", None, "Time this file of experiments.export end to end, at its resolution."
    )


def main(argv: list[str]) -> None:
    import json

    if len(argv) > 1:
        raise app.UsageError(f"unexpected arguments: {argv[1:]}")
    sizes = []
    for size in FLAGS.sizes:
        height, _, width = size.partition("x")
        if not (height.isdigit() and width.isdigit() and int(height) > 0 and int(width) > 0):
            raise app.UsageError(f"--sizes: {size!r} is not HEIGHTxWIDTH, e.g. 192x256")
        sizes.append((int(height), int(width)))
    if FLAGS.artifact is not None and not Path(FLAGS.artifact).is_file():
        raise app.UsageError(f"--artifact={FLAGS.artifact}: no such file")
    result = run(sizes=sizes, repeats=FLAGS.repeats, quick=FLAGS.quick, artifact=FLAGS.artifact)
    if FLAGS.output:
        Path(FLAGS.output).write_text(json.dumps(result, indent=1))


if __name__ == "__main__":
    _define_flags()
    command_line.run(main)
