"""The training state: what a checkpoint holds and how a fresh one is made.

`TrainState` carries everything a run needs to continue exactly where it stopped;
`create_train_state` makes a fresh one (initial parameters, Adam's state, step 0, the
run's base key); the optimiser is `gld.runs.optimizer`'s.
"""

from __future__ import annotations

from typing import Any

import flax
import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
import optax

from gld.models import global_local as model_lib
from gld.models import layers
from gld.models.flow_net import FlowNet, check_image_pair, init_params


@flax.struct.dataclass
class TrainState:
    """Everything a training run needs to continue exactly where it stopped."""

    step: jax.Array
    params: Any
    batch_stats: Any
    opt_state: Any
    rng: jax.Array  # raw key data of the run's base PRNG key

    def variables(self) -> dict[str, Any]:
        """The model variables for `model.apply`."""
        if self.batch_stats:
            return {"params": self.params, "batch_stats": self.batch_stats}
        return {"params": self.params}


def dummy_batch(batch_size: int, height: int, width: int) -> dict[str, np.ndarray]:
    """Zero inputs of the right shapes, for `model.init` and shape checks."""
    batch = {
        "image1": np.zeros((batch_size, height, width, 3), np.float32),
        "image2": np.zeros((batch_size, height, width, 3), np.float32),
        "flow": np.zeros((batch_size, height, width, 2), np.float32),
    }
    # The relative pose, for models given it (`GlobalLocal.global_source` "pose": the
    # true one; "flow_pose": the one estimated from the flow).
    for rotation_key, translation_key in model_lib.GIVEN_POSE_INPUTS.values():
        batch[rotation_key] = np.broadcast_to(
            np.eye(3, dtype=np.float32), (batch_size, 3, 3)
        ).copy()
        batch[translation_key] = np.tile(np.array([0.0, 0.0, 1.0], np.float32), (batch_size, 1))
    # The cameras, for models that read a pose against the flow.
    for key in model_lib.CAMERA_INPUTS:
        batch[key] = np.tile(np.array([0.9, 1.2, 0.5, 0.5], np.float32), (batch_size, 1))
    return batch


def init_variables(model: nn.Module, height: int, width: int, seed: int) -> dict[str, Any]:
    """Initial model variables for images of the given size (`layers.init_once`: run op
    by op, the init's forward pass of the main job's model takes 24 s on the 2-core CPU)."""
    batch = dummy_batch(1, height, width)
    args, extra = layers.model_arguments(model, batch)
    return layers.init_once(model, jax.random.key(seed), *args, **extra, train=False)


def create_train_state(
    model: nn.Module, optimizer: optax.GradientTransformation, height: int, width: int, seed: int
) -> TrainState:
    """A fresh state: initial parameters, optimiser state, step 0, the run's base key."""
    return state_of(init_variables(model, height, width, seed), optimizer, seed)


def state_of(
    variables: dict[str, Any], optimizer: optax.GradientTransformation, seed: int
) -> TrainState:
    """The state that starts training from `variables` (given or trained): a new
    optimiser state, step 0, the run's base key from `seed`."""
    params = variables["params"]
    return TrainState(
        step=jnp.zeros((), jnp.int32),
        params=params,
        batch_stats=variables.get("batch_stats", {}),
        opt_state=optimizer.init(params),
        rng=jax.random.key_data(jax.random.key(seed + 1)),
    )


def create_flow_state(
    model: FlowNet, optimizer: optax.GradientTransformation, height: int, width: int, seed: int
) -> TrainState:
    """A fresh state (gld's `TrainState`, no batch statistics) for images of a size."""
    images = jnp.zeros((1, height, width, 3), jnp.float32)
    check_image_pair(images, images, len(model.feature_channels))
    params = init_params(model, seed)
    return TrainState(
        step=jnp.zeros((), jnp.int32),
        params=params,
        batch_stats={},
        opt_state=optimizer.init(params),
        rng=jax.random.key_data(jax.random.key(seed + 1)),
    )
