"""Options: a dataclass field with its help, choices and bounds beside it.

    learning_rate: float = option(1e-3, "Peak learning rate.", above=0)

Every option of a run is one: the training loop's and the optimiser's
(`gld.runs.trainer_options`), a depth run's (`gld.runs.config.TrainConfig`), a flow run's
(`gld.runs.flow_config.FlowTrainConfig`), and the architectures of the global-local
model and the flow network (flax modules are dataclasses, so their options are fields
too). `check_option` checks a value against its field; the launchers make one flag per
option from these fields (`experiments.common.define_option_flags`), so no flag of a run
is not an option here.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping, Sequence
from typing import Any


def option(
    default: Any,
    help: str,  # noqa: A002
    choices: Sequence[str] | None = None,
    *,
    at_least: float | None = None,
    above: float | None = None,
    at_most: float | None = None,
    may_be_empty: bool = False,
) -> Any:
    """A dataclass field that launchers expose as `--<name>`. `at_least`, `above` and
    `at_most` bound a number, or every item of a list (which must not be empty unless
    `may_be_empty`); `choices` lists the values a string may take (None passes when it
    is the default: "the platform's choice")."""
    metadata = {
        "help": help,
        "choices": tuple(choices) if choices else None,
        "at_least": at_least,
        "above": above,
        "at_most": at_most,
        "may_be_empty": may_be_empty,
    }
    return dataclasses.field(default=default, metadata=metadata)


def with_default(owner: type, name: str, default: Any) -> Any:
    """`owner`'s option `name` (its help, choices and bounds) with another default, for a
    subclass whose runs start elsewhere (a flow network's learning rate)."""
    (field,) = [field for field in dataclasses.fields(owner) if field.name == name]
    return dataclasses.field(default=default, metadata=field.metadata)


def option_fields(owner: type) -> list[dataclasses.Field]:
    """The fields of a dataclass (or flax module) that are options: those with help."""
    return [field for field in dataclasses.fields(owner) if "help" in field.metadata]


def check_option(field: dataclasses.Field, value: Any) -> None:
    """Raises ValueError when `value` breaks the option's choices or bounds."""
    name, metadata = field.name, field.metadata
    if value is None and field.default is None:
        return
    if metadata["choices"] and value not in metadata["choices"]:
        raise ValueError(f"{name} must be one of {list(metadata['choices'])}, got {value!r}")
    if isinstance(value, list | tuple):
        if not value and not metadata.get("may_be_empty"):
            raise ValueError(f"{name} must not be empty")
        for item in value:
            _check_number(name, item, metadata, " (every item)", value)
        return
    _check_number(name, value, metadata, "", value)


def _check_number(name: str, value: Any, metadata: Mapping, each: str, shown: Any) -> None:
    if isinstance(value, bool) or not isinstance(value, int | float):
        return
    if not math.isfinite(value):
        raise ValueError(f"{name} must be finite, got {shown}")
    if metadata["at_least"] is not None and value < metadata["at_least"]:
        raise ValueError(f"{name} must be at least {metadata['at_least']}{each}, got {shown}")
    if metadata["above"] is not None and value <= metadata["above"]:
        raise ValueError(f"{name} must be above {metadata['above']}{each}, got {shown}")
    if metadata.get("at_most") is not None and value > metadata["at_most"]:
        raise ValueError(f"{name} must be at most {metadata['at_most']}{each}, got {shown}")


def check_options(owner: type, values: Mapping[str, Any]) -> None:
    """`check_option` for every option of `owner` that `values` holds."""
    for field in option_fields(owner):
        if field.name in values:
            check_option(field, values[field.name])
