"""How the report writes a cell: a result's metrics, the paper's numbers beside them
(`gld.paper.numbers`), a table's row and a target's verdict."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from gld.paper import numbers as paper

METRICS = ("abs_inv", "abs_rel", "s_rmse")
NOT_RUN = "not run yet"


def metric(result: dict | None, name: str = "abs_inv") -> float | None:
    if result is None:
        return None
    return result["metrics"][name]["mean"]


def metric_cells(result: dict | None, reference: float | None, missing: str = NOT_RUN) -> list[str]:
    if result is None:
        return [missing, "", "", ""]
    summary = result["metrics"]
    cells = [f"{summary['abs_inv']['mean']:.4f} ± {summary['abs_inv']['std']:.4f}"]
    cells += [f"{summary[name]['mean']:.3f}" for name in METRICS[1:]]
    cells.append(f"{summary['abs_inv']['mean'] / reference:.2f}" if reference else "")
    return cells


# Where a row of ours has the paper's numbers beside it: (table of `gld.paper.numbers`,
# the key of its row), or None.
PaperRef = tuple[str, str] | None


def paper_cell(ref: PaperRef, table: str | None = None, columns: int | None = None) -> str:
    """The paper's numbers of a row as it prints them (Abs-Inv / Abs-Rel / S-RMSE in the
    depth tables; its first `columns` only, if given); the paper's table is named when it
    is not `table`, the one the column's header names. "—" without them."""
    numbers = None if ref is None else paper.printed(*ref)
    if numbers is None:
        return "—"
    text = " / ".join(numbers[:columns])
    return text if ref[0] == table else f"{text} (`{paper.TABLES[ref[0]].label}`)"


def paper_x_mean_cell(ref: PaperRef) -> str:
    """The paper's Abs-Inv of a row as a multiple of the paper's dataset mean's."""
    multiple = None if ref is None else paper.x_mean(*ref)
    return "—" if multiple is None else f"{multiple:.2f}"


def paper_header(table: str) -> str:
    return f"paper (Scenes11, `{paper.TABLES[table].label}`) | paper x mean"


def percent_range(values: Sequence[float]) -> str:
    """18-33%: the range of fractions, in whole percent."""
    low, high = (round(100 * v) for v in (min(values), max(values)))
    return f"{low}%" if low == high else f"{low}-{high}%"


def multiple_range(values: Sequence[float]) -> str:
    """0.45-0.67x: the range of multiples."""
    low, high = f"{min(values):.2f}", f"{max(values):.2f}"
    return f"{low}x" if low == high else f"{low}-{high}x"


def table_row(cells: Sequence[Any]) -> str:
    return "| " + " | ".join(str(c) for c in cells) + " |\n"


def verdict(holds: bool | None) -> str:
    return {True: "**holds**", False: "**does not hold**", None: "not measured yet"}[holds]
