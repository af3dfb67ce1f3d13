"""The option system of every trainer: an option is a dataclass field with its help,
choices and bounds beside it.

    learning_rate: float = option(1e-3, "Peak learning rate.", above=0)

`option` makes such a field; `check_option` checks a value against it; the launchers
derive their flags from the fields that carry help (`experiments.common`). `LoopOptions`
are the options every trainer shares (`gld.runs.config.TrainConfig`,
`gld.runs.flow_config.FlowTrainConfig`): logging, periodic evaluation,
checkpoints, input workers, and the data's name and resolution.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from typing import Any

LR_SCHEDULES = ("constant", "cosine")


def option(
    default: Any,
    help: str,  # noqa: A002
    choices: Sequence[str] | None = None,
    *,
    at_least: float | None = None,
    above: float | None = None,
) -> Any:
    """A TrainConfig field that launchers expose as `--<name>`; `at_least` / `above`
    bound a number (`TrainConfig.validate`, and the flag's own check)."""
    metadata = {
        "help": help,
        "choices": tuple(choices) if choices else None,
        "at_least": at_least,
        "above": above,
    }
    return dataclasses.field(default=default, metadata=metadata)


@dataclasses.dataclass
class LoopOptions:
    """The options every trainer has (`TrainConfig`, `gld.runs.flow_config.FlowTrainConfig`):
    logging, periodic evaluation, checkpoints, input workers, and the data's name and
    resolution (set by the launcher)."""

    log_every: int = option(50, "Steps between metrics.jsonl / TensorBoard records.", at_least=1)
    eval_every: int = option(
        1000, "Steps between evaluations on the test split (0: off).", at_least=0
    )
    checkpoint_every: int = option(250, "Steps between checkpoints.", at_least=1)
    keep_checkpoints: int = option(2, "Checkpoints kept in the workdir.", at_least=1)
    eval_batch_size: int = option(
        16, "Batch size of the periodic and final evaluations.", at_least=1
    )
    eval_examples: int = option(
        0, "Periodic evaluation on the first N test pairs; 0 = all.", at_least=0
    )
    worker_count: int = option(0, "grain worker processes for the input pipeline.", at_least=0)
    dataset: str = ""
    height: int = 0
    width: int = 0


def check_schedule(lr_schedule: str, warmup_steps: int, steps: int) -> None:
    """Raises ValueError when the cosine schedule's warm-up does not end before the run
    (`gld.runs.state.learning_rate_schedule` builds the schedule)."""
    if lr_schedule == "cosine" and not 0 <= warmup_steps < steps:
        raise ValueError(
            f"warmup_steps ({warmup_steps}) must be in [0, steps ({steps})) for the cosine schedule"
        )


def check_option(field: dataclasses.Field, value: Any) -> None:
    """Raises ValueError when `value` breaks the option's choices or bounds."""
    name, metadata = field.name, field.metadata
    if metadata["choices"] and value not in metadata["choices"]:
        raise ValueError(f"{name} must be one of {list(metadata['choices'])}, got {value!r}")
    if isinstance(value, bool) or not isinstance(value, int | float):
        return
    if not math.isfinite(value):
        raise ValueError(f"{name} must be finite, got {value}")
    if metadata["at_least"] is not None and value < metadata["at_least"]:
        raise ValueError(f"{name} must be at least {metadata['at_least']}, got {value}")
    if metadata["above"] is not None and value <= metadata["above"]:
        raise ValueError(f"{name} must be above {metadata['above']}, got {value}")
