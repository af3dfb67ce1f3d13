"""The learning-rate check: which runs it trains twice, and which of the two each
comparison uses.

One shared rate could suit one model and starve another (Eigen's network collapses at
the CPU suite's 1e-3, DispNet's too: the output saturates and the gradient vanishes), so
every learned model of the main table (`RATE_CHECKED`) is also trained at a second,
lower rate (`gld.paper.scales.Scale.check_learning_rate`, runs `<run>_low_lr`); the report
shows both and compares each model at the rate with the lower training loss
(`compared_run`, from `training_loss` and `collapse`; never chosen on the test split),
and the over-fitting figure and the qualitative grid show that run. The model's runs at
the other densities and on the varying intrinsics train at that rate too
(`gld.paper.suite.with_compared_rate`); the ablations, at the suite's rate (global-local's
check chose it on the CPU suite).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from gld.paper.scales import Scale

# The main table's runs that the check trains twice.
RATE_CHECKED = (
    "global_local_1px",
    "small_encdec_1px",
    "eigen_1px",
    "dispnet_1px",
    "fcrn_1px",
    "struct2depth",
    "struct2depth_flow",
)


def low_rate_name(name: str) -> str:
    """The learning-rate check's run of a main-table run."""
    return f"{name}_low_lr"


def rate_runs(scale: Scale, name: str) -> list[str]:
    """The runs a model's comparisons may use: both rates of a checked model."""
    if scale.check_learning_rate is None or name not in RATE_CHECKED:
        return [name]
    return [name, low_rate_name(name)]


# Training losses a run logs at least (one every 50 steps, more often in a shorter run):
# the learning-rate check averages the last quarter of them, so a 150-step run is
# compared on a dozen batches, not one.
TRAINING_RECORDS = 40


def training_loss(result: dict) -> float | None:
    """A run's mean loss on its supervised training pixels (a self-supervised run's: its
    photometric loss) over the last quarter of its logged steps (what the learning-rate
    check compares; never the test split)."""
    curves = result["curves"]
    values = [value for _, value in curves["train"] or curves.get("loss", [])]
    if not values:
        return None
    return float(np.mean(values[-max(1, len(values) // 4) :]))


# A logged gradient norm below this fraction of the run's largest one has vanished. On
# the cpu_full suite the learning runs keep a quarter of their records above 1e-2 of their
# largest norm (FCRN the lowest, at 1e-2); a self-supervised run with every pixel out of
# view sits at 3e-4 to 5e-4 of it, with a rare record of 5e-2 when a batch lands a
# pixel back in view, and a saturated output at 0.
VANISHED_GRADIENT = 1e-3


def collapse(result: dict) -> tuple[int, int, int] | None:
    """(first step, count, logged steps) of the vanished gradients of a run that
    collapsed: its gradient norm is below `VANISHED_GRADIENT` of its largest logged one
    at a quarter or more of its logged steps (a saturated output no longer learns). The
    first step is the first whose norm has vanished against the largest one logged up to
    it (an early step of a run whose gradient spiked later is small against the spike,
    not vanished). None otherwise, or without a logged gradient."""
    norms = result["curves"].get("grad_norm", [])
    if not norms:
        return None
    so_far = np.maximum.accumulate([norm for _, norm in norms])
    vanished = [step for step, norm in norms if norm <= VANISHED_GRADIENT * so_far[-1]]
    if 4 * len(vanished) < len(norms):
        return None
    first = next(
        step
        for (step, norm), top in zip(norms, so_far, strict=True)
        if norm <= VANISHED_GRADIENT * top
    )
    return int(first), len(vanished), len(norms)


def compared_run(scale: Scale, name: str, result_of: Callable[[str], dict | None]) -> str | None:
    """The run of a main-table model that the comparisons use: with a learning-rate
    check, the one of its two rates with the lower training loss, unless that one
    collapsed and the other did not (a collapsed self-supervised run can have the lower
    photometric loss); None until both have finished. Else the run itself. `result_of`
    gives a run's result by its name."""
    candidates = rate_runs(scale, name)
    if len(candidates) == 1:
        return name
    results = [result_of(n) for n in candidates]
    if None in results:
        return None
    losses = [training_loss(r) for r in results]
    if None in losses:
        return None
    collapsed = [collapse(r) is not None for r in results]
    if collapsed.count(True) == 1:
        return candidates[collapsed.index(False)]
    return candidates[int(np.argmin(losses))]
