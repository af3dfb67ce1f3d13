"""An online run: a stream through a learner, scored prequentially, checkpointed, resumable.

    summary = run_online(stream, learner, "runs/online", frames=5000, meta={...})

The workdir holds:

    prequential.jsonl   one line per frame, written before the learner trains on it: the
                        partner, baselines, Abs-Inv against the truth and of the running
                        mean reference (simulation), latency, updates so far, the
                        frame's time in the learner (frame_ms)
    checkpoints/        the learner every `checkpoint_every` frames (`gld.online.checkpoint`)
    summary.json        the run: speed (frames/s, over the run and sustained after its
                        first window; frame, latency and update times p50/p90) and
                        the curve, Abs-Inv and "x mean" per window of frames
    curve.png           the curve
    view/<frame>.png    with `view_every`: the frame, its predicted inverse depth, the
                        error against the truth, the labelled pixel marked

A run that stops (killed, or `frames` reached) and is launched again resumes from its
newest checkpoint: the log is cut back to that position and the stream replayed from
there, so no labelled reading is lost and the run ends as an uninterrupted one would.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import statistics
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from tqdm import tqdm

from gld import files
from gld.arguments import ArgumentError
from gld.inference import depth_io
from gld.online import checkpoint, references
from gld.online.learner import OnlineLearner
from gld.online.stream import Frame, FrameStream
from gld.runs import workdir as workdir_lib
from gld.runs.lock import training_lock

LOG_FILE = "prequential.jsonl"
SUMMARY_FILE = "summary.json"
CURVE_FILE = "curve.png"
VIEW_DIR = "view"
LOGGED = (
    "frame",
    "partner",
    "baseline",
    "true_baseline",
    "labelled",
    "abs_inv",
    "abs_inv_mean",
    *(f"abs_inv_{name}" for name in references.NAMES),
    "latency_ms",
    "update_wait_ms",
    "updates",
)


def _read_log(path: Path, before: int) -> list[dict[str, Any]]:
    """The log's rows of frames before `before` (a resumed run's, cut back)."""
    if not path.exists():
        return []
    rows = [json.loads(line) for line in path.read_text().splitlines() if line.strip()]
    return [row for row in rows if row["frame"] < before]


def _percentiles(values: list[float]) -> dict[str, float] | None:
    if not values:
        return None
    ordered = sorted(values)
    return {
        "p50": statistics.median(ordered),
        "p90": ordered[min(len(ordered) - 1, round(0.9 * (len(ordered) - 1)))],
    }


def _median_ratio(scored: list[dict[str, Any]], key: str) -> float:
    return float(np.median([row[key] / row["abs_inv_mean"] for row in scored]))


def curve(rows: list[dict[str, Any]], window: int) -> list[dict[str, Any]]:
    """Abs-Inv and its ratio to the running mean reference ("x mean": the window's
    means) per window of frames, over the scored frames of each; the median over the
    frames of each frame's ratio ("median_x_mean"); and where the rows hold them, the
    classical references' ("<name>_x_mean", "<name>_median_x_mean"). A classical
    reference's mean is its few exploded frames' (a triangulation near the expansion's
    centre or on a degenerate pair); its median is its typical frame's."""
    points = []
    for start in range(0, (rows[-1]["frame"] + 1) if rows else 0, window):
        scored = [
            row
            for row in rows
            if start <= row["frame"] < start + window and row.get("abs_inv") is not None
        ]
        if not scored:
            continue
        error = float(np.mean([row["abs_inv"] for row in scored]))
        reference = float(np.mean([row["abs_inv_mean"] for row in scored]))
        point = {
            "frames": min(start + window, rows[-1]["frame"] + 1),
            "abs_inv": error,
            "abs_inv_mean": reference,
            "x_mean": error / reference,
            "median_x_mean": _median_ratio(scored, "abs_inv"),
            "scored": len(scored),
        }
        for name in references.NAMES:
            key = f"abs_inv_{name}"
            if all(key in row for row in scored):
                point[f"{name}_x_mean"] = float(np.mean([row[key] for row in scored])) / reference
                point[f"{name}_median_x_mean"] = _median_ratio(scored, key)
        points.append(point)
    return points


def summarise(rows: list[dict[str, Any]], window: int, seconds: float) -> dict[str, Any]:
    """The run's numbers from its log rows and the learner's wall time: frames/s over
    the whole run (its first frames compile the model), and sustained, over the frames
    after the first `window` (all of them in a shorter run)."""
    predicted = [row for row in rows if row.get("partner") is not None]
    timed = [row["frame_ms"] for row in rows if "frame_ms" in row]
    steady = timed[window:] or timed
    steady_ms = sum(steady)
    return {
        "frames": len(rows),
        "predicted": len(predicted),
        "labelled": sum(bool(row.get("labelled")) for row in predicted),
        "updates": rows[-1]["updates"] if rows else 0,
        "learner_seconds": seconds,
        "frames_per_second": len(rows) / seconds if seconds > 0 else None,
        "sustained_frames_per_second": 1e3 * len(steady) / steady_ms if steady_ms else None,
        "frame_ms": _percentiles(timed),
        "latency_ms": _percentiles([row["latency_ms"] for row in predicted]),
        "update_wait_ms": _percentiles([row["update_wait_ms"] for row in rows]),
        "curve": curve(rows, window),
    }


def write_curve(path: Path, points: list[dict[str, Any]], title: str) -> None:
    """Abs-Inv and x mean against frames seen, as a PNG."""
    import matplotlib

    matplotlib.use("Agg")
    from matplotlib import pyplot

    figure, (left, right) = pyplot.subplots(1, 2, figsize=(9, 3.2))
    frames = [point["frames"] for point in points]
    left.plot(frames, [point["abs_inv"] for point in points], label="learner")
    left.plot(frames, [point["abs_inv_mean"] for point in points], "--", label="running mean")
    left.set(xlabel="frames seen", ylabel="Abs-Inv (baselines^-1)", title=title)
    left.legend()
    right.plot(frames, [point["x_mean"] for point in points], label="learner")
    right.plot(frames, [point["median_x_mean"] for point in points], ":", label="its median frame")
    for name in references.NAMES:
        if points and all(f"{name}_median_x_mean" in point for point in points):
            medians = [point[f"{name}_median_x_mean"] for point in points]
            right.plot(frames, medians, "--", label=f"{name}, median frame")
    right.legend(fontsize="small")
    right.axhline(1.0, color="grey", linewidth=0.5)
    right.set(xlabel="frames seen", ylabel="x mean", ylim=(0, None))
    figure.tight_layout()
    files.write_atomically(path, lambda target: figure.savefig(target, dpi=100, format="png"))
    pyplot.close(figure)


def write_view(path: Path, frame: Frame, result: dict[str, Any]) -> None:
    """The frame, its predicted inverse depth, the error against the truth (the same
    scale) and the labelled pixel (a green cross), side by side."""
    inv_depth = result["inv_depth"]
    truth = result.get("true_baseline", 1.0) / frame.depth if frame.depth is not None else None
    top = (
        float(np.percentile(inv_depth, 99)) if truth is None else float(np.nanpercentile(truth, 99))
    )
    panels = [frame.image.copy(), depth_io.colourise_inverse_depth(1.0 / inv_depth, top)]
    if truth is not None:
        error = np.where(np.isfinite(truth), np.abs(truth - inv_depth), np.nan)
        panels.append(depth_io.colourise_inverse_depth(1.0 / np.maximum(error, 1e-9), top))
    if frame.reading is not None:
        u, v, _ = frame.reading
        cv2.drawMarker(panels[0], (int(round(u)), int(round(v))), (0, 255, 0), cv2.MARKER_CROSS, 7)
    path.parent.mkdir(parents=True, exist_ok=True)
    view = cv2.cvtColor(np.concatenate(panels, axis=1), cv2.COLOR_RGB2BGR)
    if not cv2.imwrite(str(path), view):
        raise OSError(f"cannot write {path}")


def run_online(
    stream: FrameStream,
    learner: OnlineLearner,
    workdir: str | Path,
    *,
    frames: int,
    meta: dict[str, Any],
    checkpoint_every: int = 250,
    window: int = 250,
    view_every: int = 0,
    progress: bool = True,
    print_fn: Callable[[str], None] = print,
) -> dict[str, Any]:
    """Runs the stream's first `frames` frames through `learner` (resuming a run's
    newest checkpoint); the summary (`summarise`, plus `meta`), also written."""
    workdir = Path(workdir)
    if frames < 1 or checkpoint_every < 1 or window < 1:
        raise ValueError(
            f"frames, checkpoint_every and window must be >= 1, got {frames}, "
            f"{checkpoint_every}, {window}"
        )
    workdir.mkdir(parents=True, exist_ok=True)
    with training_lock(workdir), contextlib.closing(checkpoint.manager(workdir)) as checkpoints:
        saved = checkpoint.saved_meta(checkpoints)
        if saved is not None:
            _check_same_run(workdir, saved, meta)
        restored = checkpoint.restore(checkpoints, learner)
        options = _Options(frames, checkpoint_every, window, view_every, progress)
        return _continue(stream, learner, workdir, checkpoints, restored, meta, options, print_fn)


# What a resumed run must share with the run it continues.
RESUMED_KEYS = ("model", "stream", "settings")


def _check_same_run(workdir: Path, saved: dict[str, Any], meta: dict[str, Any]) -> None:
    """Refuses to resume `workdir`'s run with another model, stream or learner setting,
    naming each that differs."""

    def flat(key, value):  # as the checkpoint's JSON holds it (tuples as lists)
        value = json.loads(json.dumps(value, default=str))
        if isinstance(value, dict):
            return {f"{key}.{name}": item for name, item in value.items()}
        return {key: value}

    was, now = {}, {}
    for key in RESUMED_KEYS:
        if key in saved and key in meta:
            was.update(flat(key, saved[key]))
            now.update(flat(key, meta[key]))
    changes = {
        key: (was.get(key), now.get(key))
        for key in sorted(set(was) | set(now))
        if was.get(key) != now.get(key)
    }
    if changes:
        raise ArgumentError(
            f"--workdir={workdir} holds a run made otherwise "
            f"({workdir_lib.describe_changes(changes)}): resume it as it was made, or give "
            "another --workdir"
        )


@dataclasses.dataclass(frozen=True)
class _Options:
    frames: int
    checkpoint_every: int
    window: int
    view_every: int
    progress: bool


def _continue(stream, learner, workdir, checkpoints, restored, meta, options, print_fn) -> dict:
    """`run_online` from the learner's position (restored, or 0)."""
    frames, checkpoint_every, window = options.frames, options.checkpoint_every, options.window
    view_every, progress = options.view_every, options.progress
    position = learner.next_frame
    log_path = workdir / LOG_FILE
    rows = _read_log(log_path, position)
    seconds = float(restored.get("learner_seconds", 0.0)) if restored else 0.0
    if restored:
        print_fn(f"resumed {workdir} at frame {position} ({learner.updates} updates)")
    files.write_atomically(log_path, "".join(json.dumps(row) + "\n" for row in rows))
    replay_from = max(0, position - learner.history)
    bar = tqdm(total=frames, initial=position, disable=not progress, unit="frame")
    with open(log_path, "a") as log:
        for frame in stream.frames(replay_from):
            if frame.index < position:
                learner.resume_from(frame)
                continue
            if frame.index >= frames:
                break
            start = time.perf_counter()
            result = learner.observe(frame)
            elapsed = time.perf_counter() - start
            seconds += elapsed
            row = {key: result[key] for key in LOGGED if key in result}
            row["frame_ms"] = 1e3 * elapsed
            rows.append(row)
            log.write(json.dumps(row) + "\n")
            if view_every and frame.index % view_every == 0 and "inv_depth" in result:
                write_view(workdir / VIEW_DIR / f"{frame.index:06d}.png", frame, result)
            bar.update(1)
            if "abs_inv" in result:
                bar.set_postfix(abs_inv=f"{result['abs_inv']:.4f}", updates=result["updates"])
            if learner.next_frame % checkpoint_every == 0 or learner.next_frame == frames:
                log.flush()
                checkpoint.save(checkpoints, learner, {**meta, "learner_seconds": seconds})
    bar.close()
    learner.finish()
    summary = {**meta, **summarise(rows, window, seconds)}
    files.write_atomically(workdir / SUMMARY_FILE, json.dumps(summary, indent=1) + "\n")
    if summary["curve"]:
        write_curve(workdir / CURVE_FILE, summary["curve"], meta.get("name", str(workdir)))
    return summary
