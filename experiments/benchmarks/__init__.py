"""Benchmark suites run by `python -m experiments.benchmark --suite=...`; each has `run()`."""

from __future__ import annotations

from typing import Any

import numpy as np


def format_table(results: dict[str, Any], key_width: int = 28) -> str:
    """A suite's figures as an aligned two-column table."""
    rows = []
    for key, value in results.items():
        text = f"{value:.2f}" if isinstance(value, float | np.floating) else str(value)
        rows.append(f"{key:<{key_width}} {text}")
    return "\n".join(rows)
