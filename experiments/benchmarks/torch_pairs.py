"""The PyTorch reference beside gld: running it, and comparing the alternating
(reference, gld) pairs that `experiments.benchmarks.model` measures.

`run_torch_reference` runs `../shared/bench/torch_reference.py` (the same network in
PyTorch, eager and compiled) on the CPU, or through `torch_on_device.py` on a GPU;
`summarise_pairs` compares each pair's gld row with its own reference, for the goals of
`model_tables.GOALS`.
"""

from __future__ import annotations

import json
import statistics
import subprocess
from pathlib import Path
from typing import Any

from experiments.benchmarks.model_tables import FIGURES, GOALS, MODES, spread, torch_seconds
from gld import host_memory

DEFAULT_TORCH_REFERENCE = (
    Path(__file__).resolve().parents[3] / "shared" / "bench" / "torch_reference.py"
)
# The reference's fixed problem: 256x192 images, batch 1 and 16.
TORCH_SHAPE = (192, 256)


def run_torch_reference(
    torch_python: str,
    reference: str | Path,
    repeats: int,
    compile_torch: bool,
    device: str = "cpu",
) -> dict[str, Any]:
    """Runs the PyTorch reference on `device` ("cpu": the reference's own timer; else
    `torch_on_device.py`, which times it with the device synchronised); returns its
    JSON (milliseconds) or {'error': ...}."""
    command = [torch_python, str(reference), "--repeats", str(repeats)]
    if device != "cpu":
        runner = Path(__file__).with_name("torch_on_device.py")
        command = [torch_python, str(runner), f"--device={device}", f"--reference={reference}"]
        command += ["--repeats", str(repeats)]
    if not compile_torch:
        command.append("--no-compile")
    # The reference keeps its freed memory as gld's workers do (`gld.host_memory`): the
    # same allocator settings on both sides.
    completed = subprocess.run(
        command, capture_output=True, text=True, env=host_memory.environment()
    )
    if completed.returncode != 0:
        return {"error": (completed.stderr.strip().splitlines() or ["failed"])[-1]}
    return json.loads(completed.stdout.strip().splitlines()[-1])


def torch_summary(rounds: list[dict[str, Any]]) -> dict[str, dict[str, float]]:
    """Median over rounds of each reference figure, in seconds: {mode: {key: s}}."""
    summary: dict[str, dict[str, float]] = {}
    for mode in MODES:
        figures = [torch_seconds(r)[mode] for r in rounds if mode in r]
        if figures:
            summary[mode] = {key: statistics.median(f[key] for f in figures) for key in figures[0]}
    return summary


def goal_ratios(row: dict[str, Any], torch: dict[str, dict[str, float]]) -> dict[str, float]:
    """Ratios of gld's median time to PyTorch's, for each goal of `GOALS` both have."""
    ratios = {}
    for name, figure, mode, torch_figure, _ in GOALS:
        if figure in row and torch_figure in torch.get(mode, {}):
            ratios[name] = row[figure]["median_s"] / torch[mode][torch_figure]
    return ratios


def summarise_pairs(pairs: list[dict[str, Any]]) -> dict[str, Any]:
    """The alternating (reference, gld) pairs, compared once: for each figure of
    `FIGURES`, gld's times, each mode's reference times and the pair-by-pair ratios
    ("figures"); each pair's goal ratios; the goals' median and spread; and whether the
    reference was noisy (its eager train step varies by more than 25%)."""
    measured = [p for p in pairs if "error" not in p["gld"]]
    summary: dict[str, Any] = {"pairs": len(pairs)}
    if not measured:
        return summary
    compared = [p for p in measured if p.get("torch") and "error" not in p["torch"]]
    references = [torch_seconds(p["torch"]) for p in compared]
    figures: dict[str, dict[str, list[float]]] = {}
    for figure in FIGURES:
        entry = {"gld": [p["gld"][figure]["median_s"] for p in measured if figure in p["gld"]]}
        for mode in MODES:
            paired = [
                (p["gld"][figure]["median_s"], reference[mode][f"{figure}_s"])
                for p, reference in zip(compared, references, strict=True)
                if figure in p["gld"] and mode in reference
            ]
            entry[mode] = [torch_time for _, torch_time in paired]
            entry[f"vs_{mode}"] = [gld_time / torch_time for gld_time, torch_time in paired]
        figures[figure] = entry
        if entry["gld"]:
            summary[f"gld_{figure}_s"] = spread(entry["gld"])
    summary["figures"] = figures
    summary["ratios_per_pair"] = [
        goal_ratios(p["gld"], reference) for p, reference in zip(compared, references, strict=True)
    ]
    for name, figure, mode, _, _ in GOALS:
        if figures[figure][f"vs_{mode}"]:
            summary[name] = spread(figures[figure][f"vs_{mode}"])
    eager = figures["train_b16"]["eager"]
    summary["torch_noisy"] = bool(eager and max(eager) > 1.25 * min(eager))
    return summary
