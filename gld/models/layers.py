"""Small pieces every depth network in gld shares: activation, inputs, output head."""

from __future__ import annotations

import functools
import math
from typing import Any

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np

from gld import geometry
from gld.models import convolutions

# LeakyReLU slope of every network (the paper uses LeakyReLU throughout; baselines too).
NEGATIVE_SLOPE = 0.2
# Networks start out predicting this inverse depth everywhere (scale-normalised scenes
# have inverse depths of order 0.1), so early training is not spent finding the scale.
INITIAL_INV_DEPTH = 0.1
_INV_DEPTH_OFFSET = math.log(math.expm1(INITIAL_INV_DEPTH))
MIN_INV_DEPTH = 1e-4


def leaky_relu(x: jax.Array) -> jax.Array:
    """LeakyReLU with gld's slope."""
    return jax.nn.leaky_relu(x, NEGATIVE_SLOPE)


# The conv of the baselines and the flow network: flax's, computed by
# `convolutions.conv_general_dilated` (an input map smaller than the kernel as a matmul of
# patches, which XLA's CPU runtime runs far faster). The global encoder keeps lax's (its
# comment says why).
Conv = functools.partial(nn.Conv, conv_general_dilated=convolutions.conv_general_dilated)

# The factor on the normalised flow of the global-local model and the flow-network head:
# normalised flow has a std of ~0.075 on gld_scenes, against ~0.6 for the coordinates
# and ~0.2 for the images; times 10 it is on their scale (`GlobalLocal.flow_scale`).
FLOW_SCALE = 10.0


def normalise_flow(flow: jax.Array) -> jax.Array:
    """Flow [..., H, W, 2] in pixels -> fractions of the image width and height."""
    height, width = flow.shape[-3:-1]
    return flow / jnp.asarray([width, height], flow.dtype)


def scaled_flow(flow: jax.Array, scale: float = FLOW_SCALE) -> jax.Array:
    """The flow a network reads: normalised (`normalise_flow`), times `scale`."""
    return normalise_flow(flow) * scale


# The inputs every depth model is called with, in order: model(image1, image2, flow).
MODEL_INPUTS = ("image1", "image2", "flow")


def input_keys(model) -> tuple[str, ...]:
    """The example-contract keys a depth model reads: `MODEL_INPUTS`, then the keys it
    declares in `extra_inputs` (e.g. the given relative pose), passed by keyword."""
    return MODEL_INPUTS + tuple(getattr(model, "extra_inputs", ()))


def with_coordinates(inputs: jax.Array) -> jax.Array:
    """`inputs` [B, H, W, C] with x, y in [-1, 1] appended as two channels (CoordConv),
    in the inputs' dtype: [B, H, W, C + 2]."""
    batch_size, height, width, _ = inputs.shape
    coordinates = geometry.normalised_coordinates(height, width, jnp).astype(inputs.dtype)
    coordinates = jnp.broadcast_to(coordinates, (batch_size, height, width, 2))
    return jnp.concatenate([inputs, coordinates], -1)


def global_module_inputs(
    image1: jax.Array, image2: jax.Array, normalised_flow: jax.Array, use_image_pair: bool
) -> jax.Array:
    """What the global module sees: the image pair and the (normalised, scaled) flow
    stacked on the channels, or the flow alone without the image pair."""
    if not use_image_pair:
        return normalised_flow
    return jnp.concatenate([image1, image2, normalised_flow], axis=-1)


def with_input_keys(model, keys: tuple[str, ...]) -> tuple[str, ...]:
    """`keys` (what a step reads) followed by the model's inputs it does not hold yet."""
    return keys + tuple(key for key in input_keys(model) if key not in keys)


# XLA's options for a function that runs once, a module's initialisation: the backend's
# optimisation off. The initialisers' threefry draws, one stream per layer, then compile
# in 2 s instead of 13 (the tests' tiny model on the 2-core CPU; 10 s for the main job's);
# the values agree with an optimised compile to float rounding (6e-8), as an op-by-op run.
RUN_ONCE_OPTIONS = {"xla_backend_optimization_level": 0}


def init_once(module: nn.Module, *args: Any, **kwargs: Any) -> Any:
    """`module.init(*args, **kwargs)` (the key first), compiled for the one call
    (`RUN_ONCE_OPTIONS`); traced as it is under a transformation (`jax.eval_shape` of a
    state, for a restore). Keyword arguments that are not arrays are static."""
    arrays = {k: v for k, v in kwargs.items() if isinstance(v, jax.Array | np.ndarray)}
    static = {k: v for k, v in kwargs.items() if k not in arrays}

    def init(args, arrays):
        return module.init(*args, **arrays, **static)

    if any(isinstance(leaf, jax.core.Tracer) for leaf in jax.tree_util.tree_leaves(args)):
        return init(args, arrays)
    compiled = jax.jit(init).lower(args, arrays).compile(compiler_options=RUN_ONCE_OPTIONS)
    return compiled(args, arrays)


def model_arguments(model, batch) -> tuple[tuple, dict]:
    """(args, kwargs) of a depth model's call on a batch of the example contract: the
    images and flow, then the model's `extra_inputs` by keyword."""
    args = tuple(batch[key] for key in MODEL_INPUTS)
    return args, {key: batch[key] for key in getattr(model, "extra_inputs", ())}


def apply_model(model, variables, batch, **kwargs):
    """`model.apply` on a batch of the example contract (`model_arguments`); `kwargs`
    (train, rngs, mutable) pass through."""
    args, extra = model_arguments(model, batch)
    return model.apply(variables, *args, **extra, **kwargs)


def network_inputs(image1: jax.Array, image2: jax.Array, flow: jax.Array) -> jax.Array:
    """The 8-channel input of encoders and baselines: [B, H, W, 3 + 3 + 2]."""
    return jnp.concatenate([image1, image2, normalise_flow(flow)], axis=-1)


def positive_inv_depth(logits: jax.Array) -> jax.Array:
    """Unconstrained network output -> positive inverse depth (softplus, offset so that
    a zero output means `INITIAL_INV_DEPTH`)."""
    return jax.nn.softplus(logits + _INV_DEPTH_OFFSET) + MIN_INV_DEPTH


def depth_outputs(logits: jax.Array) -> dict[str, jax.Array]:
    """[B, H, W, 1] (or [B, H, W]) logits -> {'inv_depth', 'depth'}, each [B, H, W]."""
    if logits.ndim == 4:
        logits = logits[..., 0]
    inv_depth = positive_inv_depth(logits)
    return {"inv_depth": inv_depth, "depth": 1.0 / inv_depth}


def check_inputs(image1: jax.Array, image2: jax.Array, flow: jax.Array) -> None:
    """Raises ValueError unless the images are [B, H, W, 3] and the flow [B, H, W, 2] of
    one batch and size (the call signature every depth model shares)."""
    for name, array, channels in (("image1", image1, 3), ("image2", image2, 3), ("flow", flow, 2)):
        if array.ndim != 4 or array.shape[-1] != channels:
            raise ValueError(f"{name} must be [B, H, W, {channels}], got shape {array.shape}")
    if not image1.shape[:3] == image2.shape[:3] == flow.shape[:3]:
        raise ValueError(
            f"image1 {image1.shape}, image2 {image2.shape} and flow {flow.shape} must share "
            "batch size and image size"
        )
