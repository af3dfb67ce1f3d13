"""The optimiser of every trainer: the paper's Adam, its learning-rate schedules, and the
options that choose them.

    optimizer = make_optimizer(1e-3, "cosine", steps=2000, warmup_steps=100)

`OptimizerOptions` are those options as fields (`gld.options`), shared by the depth and
the flow runs (`gld.runs.trainer_options.TrainerOptions`).
"""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import jax
import optax

from gld.options import option

LR_SCHEDULES = ("constant", "cosine")


def check_schedule(lr_schedule: str, warmup_steps: int, steps: int) -> None:
    """Raises ValueError when the cosine schedule's warm-up does not end before the run."""
    if lr_schedule == "cosine" and not 0 <= warmup_steps < steps:
        raise ValueError(
            f"warmup_steps ({warmup_steps}) must be in [0, steps ({steps})) for the cosine schedule"
        )


def learning_rate_schedule(
    learning_rate: float, schedule: str = "constant", *, steps: int = 0, warmup_steps: int = 0
) -> optax.Schedule:
    """The learning rate per step.

    "constant" is the paper's; with `warmup_steps` it first rises linearly from 0 over
    them. "cosine" rises linearly from 0 over `warmup_steps`, then decays along a cosine
    to 1% of `learning_rate` at `steps`.
    """
    if schedule == "constant":
        if warmup_steps > 0:
            return optax.linear_schedule(0.0, learning_rate, warmup_steps)
        return optax.constant_schedule(learning_rate)
    if schedule == "cosine":
        check_schedule(schedule, warmup_steps, steps)
        return optax.warmup_cosine_decay_schedule(
            init_value=0.0,
            peak_value=learning_rate,
            warmup_steps=warmup_steps,
            decay_steps=steps,
            end_value=0.01 * learning_rate,
        )
    raise ValueError(f"lr_schedule must be one of {LR_SCHEDULES}, got {schedule!r}")


def make_optimizer(
    learning_rate: float, schedule: str = "constant", *, steps: int = 0, warmup_steps: int = 0
) -> optax.GradientTransformation:
    """Adam (the paper's optimiser) with the given schedule; the rate is logged."""
    rate = learning_rate_schedule(learning_rate, schedule, steps=steps, warmup_steps=warmup_steps)
    return optax.inject_hyperparams(optax.adam)(learning_rate=rate)


class StartState(NamedTuple):
    """`toward_start`'s state: the parameters the optimiser was initialised with."""

    start: optax.Params


def toward_start(rate: float) -> optax.GradientTransformation:
    """Pulls the parameters back toward their values at `init` (L2-SP, decoupled).

    Chained after Adam: each update also moves every parameter by `-rate * (θ - θ₀)`, θ₀
    its value when the optimiser was initialised (a pretrained model's, kept in the
    optimiser state, so a checkpoint holds it). Decoupled from Adam's normalisation as
    AdamW's decay is: `rate` is the fraction of the distance from θ₀ taken back per step.
    """

    def init(params: optax.Params) -> StartState:
        return StartState(start=jax.tree.map(lambda leaf: leaf.copy(), params))

    def update(updates, state: StartState, params=None):
        if params is None:
            raise ValueError("toward_start needs the parameters in update()")
        pulled = jax.tree.map(
            lambda step, now, start: step - rate * (now - start), updates, params, state.start
        )
        return pulled, state

    return optax.GradientTransformation(init, update)


@dataclasses.dataclass
class OptimizerOptions:
    """The optimiser's options; defaults are the paper's depth runs'."""

    learning_rate: float = option(1e-4, "Adam (peak) learning rate.", above=0)
    lr_schedule: str = option(
        "constant",
        "constant (the paper's) or cosine (linear warm-up, then cosine decay to 1%).",
        LR_SCHEDULES,
    )
    warmup_steps: int = option(0, "Linear warm-up steps from a rate of 0.", at_least=0)
