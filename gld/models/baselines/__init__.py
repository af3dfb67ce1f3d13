"""The paper's baselines, chosen by name.

`LEARNED` maps a name to a Flax module class with the global-local model's call
signature, `model(image1, image2, flow, *, train=False) -> {'inv_depth', 'depth', ...}`
(multi-scale models add 'inv_depth_pyramid'); build one with `LEARNED[name]()`.
`CLASSICAL` maps a name to a geometry method with `predict(batch)`; see
`gld.models.baselines.classical`.
"""

from __future__ import annotations

import math

import flax.linen as nn
import jax
import jax.numpy as jnp

from gld.models.baselines.classical import CLASSICAL
from gld.models.baselines.dispnet import DispNet
from gld.models.baselines.eigen import EigenNet
from gld.models.baselines.fcrn import FCRN
from gld.models.baselines.self_supervised import SelfSupervised, SelfSupervisedFlow
from gld.models.baselines.small_encdec import SmallEncDec

LEARNED: dict[str, type[nn.Module]] = {
    "eigen": EigenNet,
    "dispnet": DispNet,
    "fcrn": FCRN,
    "small_encdec": SmallEncDec,
    # Self-supervised (no depth labels; `LOSS = "self_supervised"`), without / with flow.
    "struct2depth": SelfSupervised,
    "struct2depth_flow": SelfSupervisedFlow,
}

__all__ = [
    "CLASSICAL",
    "LEARNED",
    "DispNet",
    "EigenNet",
    "FCRN",
    "SelfSupervised",
    "SelfSupervisedFlow",
    "SmallEncDec",
    "parameter_count",
]


def parameter_count(model: nn.Module, height: int = 192, width: int = 256) -> int:
    """Number of trainable parameters (the 'params' collection) of a depth network.

    Shapes only: nothing is computed, so this is cheap even for the big models.

    Args:
      model: a module with the `(image1, image2, flow, *, train)` signature.
      height, width: input size (Eigen's dense layers depend on it).
    """
    image = jax.ShapeDtypeStruct((1, height, width, 3), jnp.float32)
    flow = jax.ShapeDtypeStruct((1, height, width, 2), jnp.float32)
    variables = jax.eval_shape(model.init, jax.random.key(0), image, image, flow)
    return sum(math.prod(leaf.shape) for leaf in jax.tree.leaves(variables["params"]))
