"""A suite's results as files: one per task, so a killed suite continues where it stopped.

    <results>/<task>.json        one result per task, written atomically when done
    <results>/<task>.npz         arrays a later task or the report reads

A task's name may hold a "/" (`train/<run>`, `classical/<dataset>`); its file's name
holds "__" there.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from gld import files as files_lib


def result_path(results_dir: str | Path, task: str) -> Path:
    return Path(results_dir) / f"{task.replace('/', '__')}.json"


def read_result(results_dir: str | Path, task: str) -> dict[str, Any] | None:
    """A task's result, or None if it has not finished."""
    path = result_path(results_dir, task)
    if not path.exists():
        return None
    return json.loads(path.read_text())


def write_result(results_dir: str | Path, task: str, result: dict[str, Any]) -> None:
    """A task's result, written atomically (its arrays as lists)."""

    path = result_path(results_dir, task)
    path.parent.mkdir(parents=True, exist_ok=True)
    files_lib.write_atomically(path, json.dumps(result, indent=1, default=_plain) + "\n")


def as_stored(content: Any) -> Any:
    """`content` as a result file holds it (arrays as lists, tuples as lists)."""
    return json.loads(json.dumps(content, default=_plain))


def _plain(value: Any) -> Any:
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    raise TypeError(f"not JSON serialisable: {type(value)}")
