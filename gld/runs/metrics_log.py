"""A run's metrics log: metrics.jsonl and TensorBoard.

    logger = MetricsLogger(workdir)
    logger.write(step, {"loss": 0.1})

The metrics log holds one line per (step, split). Steps logged after the last checkpoint
are trained again on resume, so `drop_metrics_after` removes the lines with step > the
restored step first (an atomic rewrite). TensorBoard gets a new event file per launch
and shows the latest value written for a step.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import jax

from gld.files import write_atomically

METRICS_FILE = "metrics.jsonl"


def read_metrics(workdir: str | Path) -> list[dict[str, Any]]:
    """The records of a run's metrics.jsonl, in order (none without the file); a line cut
    short by a killed writer is skipped."""
    path = Path(workdir) / METRICS_FILE
    if not path.exists():
        return []
    records = []
    for line in path.read_text().splitlines():
        try:
            records.append(json.loads(line))
        except ValueError:
            continue
    return records


def drop_metrics_after(workdir: str | Path, step: int) -> int:
    """Removes the metrics.jsonl lines of steps after `step` (and any line cut short by a
    killed writer), rewriting the file atomically; returns how many were removed."""
    path = Path(workdir) / METRICS_FILE
    if not path.exists():
        return 0
    kept, dropped = [], 0
    for line in path.read_text().splitlines():
        if not line.strip():
            continue
        try:
            record_step = json.loads(line)["step"]
        except (ValueError, KeyError, TypeError):
            dropped += 1
            continue
        if record_step > step:
            dropped += 1
        else:
            kept.append(line + "\n")
    if dropped:
        write_atomically(path, "".join(kept))
    return dropped


class MetricsLogger:
    """metrics.jsonl + TensorBoard, written by process 0 only."""

    def __init__(self, workdir: Path):
        self.enabled = jax.process_index() == 0
        self.path = Path(workdir) / METRICS_FILE
        self.writer = None
        if self.enabled:
            from tensorboardX import SummaryWriter

            self.writer = SummaryWriter(str(Path(workdir) / "tensorboard"))

    def write(self, step: int, values: dict[str, float], prefix: str = "train") -> None:
        if not self.enabled:
            return
        record = {"step": step, "split": prefix, **values}
        with self.path.open("a") as stream:
            stream.write(json.dumps(record) + "\n")
        for name, value in values.items():
            if isinstance(value, int | float) and math.isfinite(value):
                self.writer.add_scalar(f"{prefix}/{name}", value, step)
        self.writer.flush()

    def close(self) -> None:
        if self.writer is not None:
            self.writer.close()
