"""Options: a dataclass field with its help, choices and bounds beside it, and the
command-line flags made from such fields.

    learning_rate: float = option(1e-3, "Peak learning rate.", above=0)

Every option of a run is one: the training loop's and the optimiser's
(`gld.runs.shared_options`), a depth run's (`gld.runs.config.TrainConfig`), a flow run's
(`gld.runs.flow_config.FlowTrainConfig`), and the architectures of the global-local
model and the flow network (flax modules are dataclasses, so their options are fields
too). `check_option` checks a value against its field, `define_flags` makes one absl
flag per option and `flag_values` reads them back: the launchers have no flag of a run
that is not an option here.
"""

from __future__ import annotations

import dataclasses
import math
import sys
from collections.abc import Iterable, Mapping, Sequence
from typing import Any

from absl import flags


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


def define_flags(
    fields: Iterable[dataclasses.Field],
    defaults: Mapping[str, Any] | None = None,
    flag_set: flags.FlagValues = flags.FLAGS,
) -> None:
    """One absl flag per option field, typed by its choices or its default, with its help
    and bounds (checked when the command line is parsed, so a bad value stops a launcher
    before it does anything); `defaults` replaces some defaults for one launcher."""
    fields = list(fields)
    defaults = dict(defaults or {})
    # The flags belong to the module that asks for them (a launcher, as `--help` and
    # `--helpfull` list them), not to this one; absl names the main module by its file.
    module_name = sys._getframe(1).f_globals["__name__"]
    module_name = sys.argv[0] if module_name == "__main__" else module_name
    unknown = sorted(set(defaults) - {field.name for field in fields})
    if unknown:
        raise ValueError(f"no option(s) {unknown} to give a default")
    for field in fields:
        name, metadata = field.name, field.metadata
        default = defaults.get(name, field.default)
        help_text = metadata["help"]
        low, high = metadata["at_least"], metadata.get("at_most")
        if metadata["choices"]:
            flags.DEFINE_enum(
                name, default, list(metadata["choices"]), help_text, flag_values=flag_set
            )
        elif isinstance(default, bool):
            flags.DEFINE_bool(
                name, default, help_text, flag_values=flag_set, module_name=module_name
            )
        elif isinstance(default, int):
            flags.DEFINE_integer(
                name, default, help_text, low, high, flag_values=flag_set, module_name=module_name
            )
        elif isinstance(default, float):
            flags.DEFINE_float(
                name, default, help_text, low, high, flag_values=flag_set, module_name=module_name
            )
        elif isinstance(default, list | tuple):
            flags.DEFINE_list(
                name, [str(value) for value in default], help_text, flag_values=flag_set
            )
        else:
            flags.DEFINE_string(
                name, default, help_text, flag_values=flag_set, module_name=module_name
            )
        if metadata["above"] is not None:
            above = metadata["above"]
            flags.register_validator(
                name,
                lambda value, above=above: value is None or value > above,
                message=f"--{name} must be above {above}",
                flag_values=flag_set,
            )


def flag_values(
    fields: Iterable[dataclasses.Field], flag_set: flags.FlagValues = flags.FLAGS
) -> dict[str, Any]:
    """The values of the option fields' flags (those defined), lists of numbers as
    numbers; an option left at None (a speed-only choice) is omitted. Raises ValueError
    naming a list flag whose items are not numbers."""
    values = {}
    for field in fields:
        if field.name not in flag_set:
            continue
        value = flag_set[field.name].value
        if isinstance(field.default, list | tuple) and isinstance(value, list):
            value = _numbers(field, value)
        if value is not None:
            values[field.name] = value
    return values


def _numbers(field: dataclasses.Field, items: list[str]) -> list[int | float]:
    kind = type(field.default[0]) if field.default else int
    try:
        return [kind(item) for item in items]
    except ValueError:
        noun = "integers" if kind is int else "numbers"
        raise ValueError(f"{field.name} must be {noun}, got {items}") from None
