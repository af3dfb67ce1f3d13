"""The model benchmark's tables: the printed one, and the README's speed table.

`experiments.benchmarks.model` measures; this module formats what it measured.
`markdown_table` writes the README's table (`python -m experiments.benchmark --readme`),
`replace_readme_table` puts it between the README's markers for the result's backend (the
CPU's or the GPU's), and `readme_from` does both from a stored result (`--readme_from`).
"""

from __future__ import annotations

import json
import statistics
from collections.abc import Sequence
from pathlib import Path
from typing import Any

# The figures measured against the reference: gld's row key (+ "_s" in the reference's).
FIGURES = ("train_b16", "forward_b16", "forward_b1")

# Goals of gld's time against PyTorch's: (name, gld figure, reference mode and figure, bound).
GOALS = (
    ("train_b16_vs_eager", "train_b16", "eager", "train_b16_s", 0.5),
    ("train_b16_vs_compiled", "train_b16", "compiled", "train_b16_s", 1.0),
    ("forward_b16_vs_compiled", "forward_b16", "compiled", "forward_b16_s", 1.0),
    ("forward_b1_vs_eager", "forward_b1", "eager", "forward_b1_s", 1.0),
)


# The reference's modes.
MODES = ("eager", "compiled")


def torch_seconds(figures: dict[str, Any]) -> dict[str, dict[str, float]]:
    """One reference run's figures in seconds: {mode: {"train_b16_s": ...}}."""
    return {
        mode: {key.replace("_ms", "_s"): value / 1000 for key, value in figures[mode].items()}
        for mode in MODES
        if mode in figures
    }


def spread(values: Sequence[float]) -> dict[str, float]:
    return {"median": statistics.median(values), "min": min(values), "max": max(values)}


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
    # The accelerator's own peak where there is one, else the host's.
    peak = row.get("peak_device_mb", row["peak_rss_mb"])
    cells += [f"{train['median_s']:8.3f}", f"{peak:8.0f}"]
    for figure in (row[f"forward_b{max(forward_batch_sizes, default=1)}"], train):
        cells.append(f"{figure['gflops_per_s']:7.1f}" if figure["gflops_per_s"] else "      -")
    return " ".join(cells)


def format_table(result: dict[str, Any]) -> str:
    """The printed table: one line per row, then the reference, the pairs and the goals."""
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
        f"{settings['height']}x{settings['width']}, "
        + (
            f"{settings['cpu_devices']} CPU devices; "
            if result.get("backend", "cpu") == "cpu"
            else f"one {result['backend']} device (peak MB: its memory); "
        )
        + "compile = train step [s]; b1 = forward latency [ms]; pr/s = forward pairs/s; "
        "train = Adam step [s]; GF/s = cost-analysis flops / median time",
        " ".join(header),
    ]
    lines += [format_row(row, train_batch, sizes) for row in result["rows"]]
    gemm = result.get("gemm", {})
    if "best_gflops_per_s" in gemm:
        lines.append(
            f"float32 GEMM {gemm['size']}: {gemm['best_gflops_per_s']:.0f} GFLOP/s best, "
            f"{gemm['median_gflops_per_s']:.0f} median"
        )
    torch = result["torch"]["median_s"]
    for mode, figures in torch.items():
        lines.append(
            f"{'torch ' + mode:28s} b1 {figures['forward_b1_s'] * 1e3:.1f} ms, "
            f"b16 {16 / figures['forward_b16_s']:.1f} pairs/s, "
            f"train16 {figures['train_b16_s']:.3f} s"
        )
    summary = result.get("summary", {})
    for index, ratios in enumerate(summary.get("ratios_per_pair", [])):
        cells = ", ".join(f"{k} {v:.2f}" for k, v in ratios.items())
        lines.append(f"pair {index + 1}: {cells}")
    for name, *_, bound in GOALS:
        if name in summary:
            figures = summary[name]
            lines.append(
                f"{name}: median {figures['median']:.2f} "
                f"({figures['min']:.2f}-{figures['max']:.2f}), goal <= {bound:g}"
            )
    if summary.get("torch_noisy"):
        lines.append("the reference was noisy: its train step varied by more than 25% across pairs")
    if "train_share_of_gemm_peak" in summary:
        shares = ", ".join(f"{share:.0%}" for share in summary["train_share_of_gemm_peak"])
        lines.append(f"train step's share of the GEMM peak: {shares} (goal >= 25%)")
    lines.append(f"default formulation: {result['default_formulation']}")
    return "\n".join(lines)


def paired_formulation(result: dict[str, Any]) -> str:
    """The formulation measured against the reference (results before it was recorded
    were CPU runs, paired with the CPU default)."""
    return result.get("paired_formulation", result["default_formulation"]["cpu"])


def markdown_table(result: dict[str, Any], commit: str, source: str = "benchmark.json") -> str:
    """The README's speed table (the default formulation's pairs against PyTorch)."""
    summary, settings = result["summary"], result["settings"]
    gemm = result.get("gemm", {})
    backend = result.get("backend", "cpu")
    paired = paired_formulation(result)
    if backend == "cpu":
        where = f"the CPU default `{paired}` on {settings['cpu_devices']} CPU devices"
    else:
        where = f"the {backend.upper()} default `{paired}` on one device"
    peak_note = ""
    if backend == "gpu":
        peak_note = " at JAX's default precision, TF32 on the GPU's matrix units"
    torch_version = next(
        (p["torch"].get("torch") for p in result["pairs"] if p["torch"] and "torch" in p["torch"]),
        None,
    )
    lines = [
        f"Measured {result['date']} at commit {commit} on {result['machine']} (load average "
        f"{settings['load_average'][0]:.1f} at the end), {settings['width']}x"
        f"{settings['height']}, {where}, PyTorch {torch_version or '-'} "
        f"({settings['pairs']} alternating pairs; medians over {settings['repeats']} calls, "
        "spread = the pairs' min-max):",
        "",
        "| measure | gld | PyTorch eager | PyTorch compiled | gld / eager | gld / compiled |",
        "|---|---|---|---|---|---|",
    ]
    # Seconds for the CPU's batches of 16; milliseconds for the rest.
    in_seconds = {"train_b16", "forward_b16"} if backend == "cpu" else set()
    labels = {
        "train_b16": "Adam train step, batch 16",
        "forward_b16": "forward, batch 16",
        "forward_b1": "forward, batch 1",
    }
    for figure, entry in summary["figures"].items():
        scale, digits, unit = (1, 3, "s") if figure in in_seconds else (1000, 2, "ms")
        if figure == "forward_b1" and backend == "cpu":
            digits = 1

        def cell(values: list[float], scale: float = scale, digits: int = digits) -> str:
            if not values:
                return "-"
            figures = spread([v * scale for v in values])
            return (
                f"{figures['median']:.{digits}f} ({figures['min']:.{digits}f}-"
                f"{figures['max']:.{digits}f})"
            )

        ratios = [" / ".join(f"{r:.2f}" for r in entry[f"vs_{mode}"]) or "-" for mode in MODES]
        lines.append(
            f"| {labels[figure]} [{unit}] | {cell(entry['gld'])} | {cell(entry['eager'])} | "
            f"{cell(entry['compiled'])} | {ratios[0]} | {ratios[1]} |"
        )
    lines.append("")
    notes = []
    if "best_gflops_per_s" in gemm:
        shares = summary.get("train_share_of_gemm_peak", [])
        notes.append(
            f"The machine's float32 GEMM ({gemm['size']}x{gemm['size']} matmul through XLA"
            f"{peak_note}): "
            f"{gemm['best_gflops_per_s']:,.0f} GFLOP/s best, {gemm['median_gflops_per_s']:,.0f} "
            "median; the train step reaches "
            + ", ".join(f"{share:.0%}" for share in shares)
            + " of it."
        )
    if summary.get("torch_noisy"):
        notes.append(
            "The reference was noisy: its train step varied by more than 25% across pairs."
        )
    notes.append("Ratios are per pair (gld measured right after the reference).")
    train_key = f"train_b{settings.get('train_batch_size', 16)}"
    others = [
        f"`{row['formulation']}` {row[train_key]['median_s']:.2f} s"
        if backend == "cpu"
        else f"`{row['formulation']}` {row[train_key]['median_s'] * 1e3:.2f} ms"
        for row in result.get("rows", [])
        if "error" not in row and row["formulation"] != paired
    ]
    if others:
        notes.append(
            "The train step of the other formulations in the same run: "
            + ", ".join(others)
            + "; every row (compile time, p90, batch 64, peak memory, GFLOP/s) is in "
            f"`{source}`."
        )
    lines.append(" ".join(notes))
    return "\n".join(lines)


README_START = (
    "<!-- speed table: python -m experiments.benchmark "
    "--torch_python=.torchref/bin/python --readme -->"
)
README_END = "<!-- end of speed table -->"
# The GPU's table: measured on a GPU machine, written into the README from its JSON.
GPU_README_START = (
    "<!-- GPU speed table: python -m experiments.benchmark --torch_python=python3 "
    "--torch_device=cuda, then --readme_from=benchmark.json -->"
)
GPU_README_END = "<!-- end of GPU speed table -->"
README_MARKERS = {"cpu": (README_START, README_END), "gpu": (GPU_README_START, GPU_README_END)}


def replace_readme_table(readme: str, table: str, backend: str = "cpu") -> str:
    """`readme` with the text between the `backend`'s speed table markers replaced by
    `table`."""
    start, end = README_MARKERS[backend]
    if start not in readme or end not in readme:
        raise ValueError(f"the README has no speed table markers ({start} ... {end})")
    head, rest = readme.split(start, 1)
    _, tail = rest.split(end, 1)
    return f"{head}{start}\n{table}\n{end}{tail}"


def rewrite_readme(
    readme: Path, result: dict[str, Any], commit: str, source: str = "benchmark.json"
) -> str:
    """Puts `result`'s table between `readme`'s markers for its backend (`source`: where
    the table says every row is); returns the backend."""
    backend = result.get("backend", "cpu")
    table = markdown_table(result, commit, source)
    readme.write_text(replace_readme_table(readme.read_text(), table, backend))
    return backend


def readme_from(readme: Path, path: Path) -> str:
    """`readme`'s table from a stored model-suite result (`experiments.benchmark`'s
    `--output`), at the commit it records; ValueError, with `readme` untouched, if `path`
    holds no complete one. Returns the backend."""
    try:
        record = json.loads(Path(path).read_text())
    except (OSError, ValueError) as error:
        raise ValueError(f"cannot read a result from {path}: {error}") from None
    if not isinstance(record, dict) or record.get("suite") != "model":
        raise ValueError(f"{path} is not a model-suite result")
    try:
        return rewrite_readme(
            readme, record["result"], record.get("commit") or "unknown", str(path)
        )
    except (KeyError, TypeError, AttributeError) as error:
        raise ValueError(f"{path} is not a complete model-suite result (no {error})") from None
