"""Options: a field with its help, choices and bounds, and the flags made from it."""

import dataclasses
from collections.abc import Sequence

import pytest
from absl import flags

from gld import options
from gld.models.flow_net import FlowNet
from gld.models.global_local import GlobalLocal
from gld.runs.config import TrainConfig
from gld.runs.flow_config import FlowTrainConfig
from gld.runs.trainer_options import TrainerOptions


@dataclasses.dataclass
class Example:
    rate: float = options.option(0.5, "A rate.", above=0, at_most=1)
    count: int = options.option(3, "A count.", at_least=1)
    kind: str = options.option("a", "A kind.", ("a", "b"))
    choice: str | None = options.option(None, "The platform's unless given.", ("x", "y"))
    widths: Sequence[int] = options.option((4, 8), "Widths.", at_least=1)
    extras: Sequence[int] = options.option((), "Extras.", at_least=1, may_be_empty=True)
    switch: bool = options.option(False, "A switch.")
    name: str = ""  # no help: set by a launcher, not a flag


def _field(name: str) -> dataclasses.Field:
    return {field.name: field for field in dataclasses.fields(Example)}[name]


def test_options_are_the_fields_with_help():
    assert [field.name for field in options.option_fields(Example)] == [
        "rate",
        "count",
        "kind",
        "choice",
        "widths",
        "extras",
        "switch",
    ]


@pytest.mark.parametrize(
    "name, value, message",
    [
        ("rate", 0.0, "rate must be above 0"),
        ("rate", 1.5, "rate must be at most 1"),
        ("rate", float("nan"), "rate must be finite"),
        ("count", 0, "count must be at least 1"),
        ("kind", "c", r"kind must be one of \['a', 'b'\]"),
        ("choice", "z", "choice must be one of"),
        ("widths", [4, 0], r"widths must be at least 1 \(every item\), got \[4, 0\]"),
        ("widths", [], "widths must not be empty"),
    ],
)
def test_a_value_out_of_bounds_is_named(name, value, message):
    with pytest.raises(ValueError, match=message):
        options.check_option(_field(name), value)


def test_values_within_bounds_pass():
    for name, value in [
        ("rate", 1.0),
        ("count", 1),
        ("kind", "b"),
        ("choice", None),  # the default: the platform's choice
        ("widths", [1]),
        ("extras", []),
        ("switch", True),
    ]:
        options.check_option(_field(name), value)


def test_a_subclass_changes_a_default_and_keeps_the_rest():
    flow, depth = FlowTrainConfig(), TrainConfig()
    assert (flow.learning_rate, depth.learning_rate) == (1e-3, 1e-4)
    fields = {
        cls: {f.name: f for f in dataclasses.fields(cls)} for cls in (TrainConfig, FlowTrainConfig)
    }
    for name in ("learning_rate", "lr_schedule", "warmup_steps", "steps", "batch_size"):
        assert fields[TrainConfig][name].metadata == fields[FlowTrainConfig][name].metadata
    # Both trainers' shared options are one definition.
    shared = {field.name for field in options.option_fields(TrainerOptions)}
    assert {"learning_rate", "lr_schedule", "warmup_steps", "steps", "seed"} <= shared
    assert shared <= {field.name for field in options.option_fields(FlowTrainConfig)}
    assert shared <= {field.name for field in options.option_fields(TrainConfig)}


def test_flags_are_made_from_the_options_with_their_types_and_bounds():
    flag_set = flags.FlagValues()
    options.define_flags(options.option_fields(Example), {"count": 5}, flag_set)
    flag_set(["prog", "--rate=0.25", "--widths=2,3", "--kind=b", "--switch"])
    assert options.flag_values(options.option_fields(Example), flag_set) == {
        "rate": 0.25,
        "count": 5,  # the launcher's default
        "kind": "b",
        "widths": [2, 3],
        "extras": [],
        "switch": True,
    }  # "choice" left at None is omitted
    assert flag_set["rate"].help == "A rate."
    for bad in ("--rate=0", "--rate=2", "--count=0", "--kind=c"):
        fresh = flags.FlagValues()
        options.define_flags(options.option_fields(Example), flag_set=fresh)
        with pytest.raises(flags.IllegalFlagValueError):
            fresh(["prog", bad])


def test_a_list_flag_of_words_is_named():
    flag_set = flags.FlagValues()
    options.define_flags(options.option_fields(Example), flag_set=flag_set)
    flag_set(["prog", "--widths=4,wide"])
    with pytest.raises(ValueError, match=r"widths must be integers, got \['4', 'wide'\]"):
        options.flag_values(options.option_fields(Example), flag_set)


def test_a_launcher_default_must_name_an_option():
    with pytest.raises(ValueError, match="coutn"):
        options.define_flags(options.option_fields(Example), {"coutn": 2}, flags.FlagValues())


def test_every_option_of_a_run_has_help_and_a_valid_default():
    for owner in (TrainConfig, FlowTrainConfig, GlobalLocal, FlowNet):
        fields = options.option_fields(owner)
        assert fields, owner
        for field in fields:
            assert field.metadata["help"].strip(), (owner, field.name)
            options.check_option(field, field.default)
