"""Every learned depth network by name, and what a run stores of one.

    model = registry.make_model("global_local", **config)
    values = registry.full_config("global_local", config)   # every argument, defaults in

`MODELS` maps `--model` names to modules; `full_config` and `check_config` complete and
check a model's options before anything is built (each option's help, choices and bounds
sit beside its field in the model, `gld.options`), and `FIELDS_ADDED_LATER` completes a
stored config that predates an option with the value its run was trained with. The
models themselves know nothing of the registry.
"""

from __future__ import annotations

import dataclasses

import flax.linen as nn
import jax

from gld.models import baselines
from gld.models.flow_depth import FlowNetHead, GlobalLocalFlowNet, check_flow_net_workdir
from gld.models.global_local import (
    ENCODER_POSE_READERS,
    GIVEN_POSE_INPUTS,
    POSE_READERS,
    GlobalLocal,
)
from gld.options import check_options

# Every learned depth network, by name (`--model`).
MODELS: dict[str, type[nn.Module]] = {
    "global_local": GlobalLocal,
    **baselines.LEARNED,
    # The learned flow network inside the depth model (`gld.models.flow_depth`).
    "global_local_flow_net": GlobalLocalFlowNet,
    "flow_net_head": FlowNetHead,
}

# Architecture fields added after the first runs were written, with the value those
# runs were trained with: a stored config without the field was trained with this.
FIELDS_ADDED_LATER: dict[str, dict[str, object]] = {
    "global_local": {
        "flow_scale": 1.0,
        "global_norm": "none",
        "modulation_scale": 0.2,
        "global_source": "encoder",
        "encoder_norm": "none",
        "encoder_coordinates": False,
        "pose_refinement_steps": 0,
        "pose_refinement_starts": 1,
        "pose_rotation_error": 0.0,
        "pose_translation_error": 0.0,
        "border": "zero",
        "derotate_flow": False,
        "parallax_depth": False,
    },
    "global_local_flow_net": {"global_local": {}},
}


def complete_stored_config(name: str, config: dict) -> dict:
    """A stored model config with the fields it predates filled in as it was trained."""
    return {**FIELDS_ADDED_LATER.get(name, {}), **config}


def full_config(name: str, config: dict) -> dict:
    """Every constructor argument of a registered model: `config` over the defaults
    (stored in a workdir, so that a later change of a default cannot change a run)."""
    if name not in MODELS:
        raise ValueError(f"unknown model {name!r}; valid: {sorted(MODELS)}")
    defaults = {
        field.name: field.default
        if field.default is not dataclasses.MISSING
        else field.default_factory()
        for field in dataclasses.fields(MODELS[name])
        if field.name not in ("parent", "name")
        and (
            field.default is not dataclasses.MISSING
            or field.default_factory is not dataclasses.MISSING
        )
    }
    unknown = sorted(set(config) - set(defaults))
    if unknown:
        raise ValueError(f"model {name!r} has no option(s) {unknown}; valid: {sorted(defaults)}")
    values = {**defaults, **config}
    return {k: list(v) if isinstance(v, tuple) else v for k, v in values.items()}


def encoder_pose(values: dict) -> bool:
    """Whether a global-local model of full config `values` infers g from its inputs and
    g can stand for the camera motion (`global_params_pose`): the global module, the
    encoder as the source, six global parameters."""
    return bool(
        values["use_global_module"]
        and values["global_source"] == "encoder"
        and values["global_dim"] == 6
    )


def reads_encoder_pose(values: dict) -> bool:
    """Whether such a model can also refine its encoder's pose on the flow:
    `encoder_pose`, and the flow is an input."""
    return encoder_pose(values) and bool(values["use_flow"])


def reads_pose(values: dict) -> bool:
    """Whether a global-local model of full config `values` has a pose as g (six global
    parameters, from its encoder or given) and the flow, and so can subtract the flow of
    g's rotation and triangulate the flow under g."""
    return bool(values["use_global_module"] and values["global_dim"] == 6 and values["use_flow"])


def check_config(name: str, config: dict) -> None:
    """Raises ValueError naming the first option of `config` a registered model cannot be
    built with: unknown, a choice or bound broken, lists of mismatched length."""
    values = full_config(name, config)
    if "flow_net_workdir" in values:
        check_flow_net_workdir(values["flow_net_workdir"])
    if name == "global_local_flow_net":
        try:
            check_config("global_local", values["global_local"])
        except ValueError as error:
            raise ValueError(f"global_local: {error}") from None
    if name != "global_local":
        return
    check_options(GlobalLocal, values)
    for option in ("pose_rotation_error", "pose_translation_error"):
        if values[option] and not (
            values["use_global_module"] and values["global_source"] == "pose"
        ):
            raise ValueError(
                f"{option} is the error of a given pose: it needs global_source pose (and the "
                "global module)"
            )
    if values["global_source"] in GIVEN_POSE_INPUTS and values["global_dim"] != 6:
        raise ValueError(
            f'global_source="{values["global_source"]}" gives 6 global parameters; global_dim '
            f"is {values['global_dim']}"
        )
    defaults = full_config(name, {})
    for option, what in ENCODER_POSE_READERS.items():
        if values[option] != defaults[option] and not encoder_pose(values):
            raise ValueError(
                f"{option} {what}: it needs the global module, global_source encoder and "
                "global_dim 6"
            )
    for option, what in {**ENCODER_POSE_READERS, **POSE_READERS}.items():
        if values[option] != defaults[option] and not values["use_flow"]:
            raise ValueError(
                f"{option} {what}, which a model without the flow (use_flow false) must not read"
            )
        if values[option] != defaults[option] and not reads_pose(values):
            raise ValueError(f"{option} {what}: it needs the global module and global_dim 6")
    if values["pose_refinement_starts"] > 1 and not values["pose_refinement_steps"]:
        raise ValueError(
            "pose_refinement_starts searches around the encoder's pose before its refinement: "
            "it needs pose_refinement_steps"
        )
    if len(values["encoder_channels"]) != len(values["encoder_strides"]):
        raise ValueError(
            f"encoder_channels {values['encoder_channels']} and encoder_strides "
            f"{values['encoder_strides']} must have the same length"
        )


def make_model(name: str = "global_local", **config) -> nn.Module:
    """Builds a registered model; `config` holds its constructor arguments."""
    if name not in MODELS:
        raise ValueError(f"unknown model {name!r}; valid: {sorted(MODELS)}")
    return MODELS[name](**config)


def parameter_counts(params) -> dict[str, int]:
    """Parameters per top-level module and in total."""
    counts = {
        name: sum(int(x.size) for x in jax.tree_util.tree_leaves(subtree))
        for name, subtree in params.items()
    }
    counts["total"] = sum(counts.values())
    return counts
