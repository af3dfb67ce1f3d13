"""Options: a field with its help, choices and bounds."""

import dataclasses

import pytest
from option_checks import Example

from gld import options
from gld.models.flow_net import FlowNet
from gld.models.global_local import GlobalLocal
from gld.runs.config import TrainConfig
from gld.runs.flow_config import FlowTrainConfig
from gld.runs.trainer_options import TrainerOptions


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


def test_every_option_of_a_run_has_help_and_a_valid_default():
    for owner in (TrainConfig, FlowTrainConfig, GlobalLocal, FlowNet):
        fields = options.option_fields(owner)
        assert fields, owner
        for field in fields:
            assert field.metadata["help"].strip(), (owner, field.name)
            options.check_option(field, field.default)
