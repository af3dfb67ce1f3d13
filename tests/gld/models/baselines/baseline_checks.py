"""Shared checks of the learned baselines: output shapes and a few training steps.

A plain module (not a conftest.py, whose module name would shadow tests/conftest.py).
"""

import jax
import jax.numpy as jnp
import numpy as np

from gld.losses import supervised as gld_losses
from gld.runs import state as state_lib
from gld.runs.optimizer import make_optimizer
from gld.training import trainer as train

# The 'rbg' generator compiles several times faster than threefry on CPU; model
# initialisation is most of a tiny test's time otherwise.
INIT_KEY_IMPL = "rbg"


def tiny_batch(batch_size: int, height: int, width: int, seed: int = 0):
    """Random pair + flow, a smooth target inverse depth and ~10% supervised pixels."""
    rng = np.random.default_rng(seed)
    image1 = rng.uniform(-0.5, 0.5, (batch_size, height, width, 3)).astype(np.float32)
    image2 = rng.uniform(-0.5, 0.5, (batch_size, height, width, 3)).astype(np.float32)
    flow = rng.normal(0.0, 2.0, (batch_size, height, width, 2)).astype(np.float32)
    columns = np.linspace(0.0, 1.0, width, dtype=np.float32)
    target = 0.3 + 0.2 * columns[None, None, :] * np.ones((batch_size, height, 1), np.float32)
    mask = rng.uniform(size=(batch_size, height, width)) < 0.1
    return image1, image2, flow, target, mask


def train_tiny(model, *, height=32, width=32, steps=35, learning_rate=1e-3):
    """The trainer's step (`train.make_train_step`, Adam) on one tiny batch, with only
    the sparse L1 inverse-depth term (smoothness weight 0); multi-scale models get it at
    every scale, as in training.

    Returns:
      the losses of every step (each of the parameters before that step's update), the
      outputs of the trained model in evaluation mode (`train=False`), and its variables.
    """
    image1, image2, flow, target, mask = tiny_batch(2, height, width)
    batch = {
        "image1": image1,
        "image2": image2,
        "flow": flow,
        "depth": 1.0 / target,
        "sparse_mask": mask,
    }
    variables = jax.jit(model.init)(jax.random.key(0, impl=INIT_KEY_IMPL), image1, image2, flow)
    optimizer = make_optimizer(learning_rate)
    # As `state_lib.create_train_state`, but initialised with the faster key.
    state = state_lib.TrainState(
        step=jnp.zeros((), jnp.int32),
        params=variables["params"],
        batch_stats=variables.get("batch_stats", {}),
        opt_state=optimizer.init(variables["params"]),
        rng=jax.random.key_data(jax.random.key(1, impl=INIT_KEY_IMPL)),
    )
    step = jax.jit(
        train.make_train_step(
            model=model,
            optimizer=optimizer,
            loss_weights=gld_losses.LossWeights(depth=1.0, smoothness=0.0),
        )
    )

    losses = []
    for index in range(steps):
        dropout_key = jax.random.key(index, impl=INIT_KEY_IMPL)
        state, step_metrics = step(state, batch, dropout_key)
        losses.append(float(step_metrics["loss"]))
    assert np.all(np.isfinite(losses)), losses
    assert int(state.step) == steps

    trained = state.variables()
    outputs = jax.jit(lambda variables: model.apply(variables, image1, image2, flow))(trained)
    return np.asarray(losses), jax.tree.map(np.asarray, outputs), trained


def output_shapes(model, height, width, batch_size=2):
    """Abstract forward pass (shapes only, nothing computed) -> the output shape tree."""
    image = jax.ShapeDtypeStruct((batch_size, height, width, 3), jnp.float32)
    flow = jax.ShapeDtypeStruct((batch_size, height, width, 2), jnp.float32)
    variables = jax.eval_shape(model.init, jax.random.key(0), image, image, flow)
    outputs = jax.eval_shape(
        lambda variables, image, flow: model.apply(variables, image, image, flow),
        variables,
        image,
        flow,
    )
    assert outputs["inv_depth"].shape == (batch_size, height, width)
    assert outputs["depth"].shape == (batch_size, height, width)
    return outputs


def check_trained_outputs(losses, outputs, height=32, width=32):
    """The common assertions on `train_tiny`'s results."""
    assert losses[-1] < 0.6 * losses[0], losses
    assert outputs["inv_depth"].shape == (2, height, width)
    assert np.all(outputs["inv_depth"] > 0)
    np.testing.assert_allclose(outputs["depth"] * outputs["inv_depth"], 1.0, rtol=1e-5)
    for scale in outputs.get("inv_depth_pyramid", ()):
        assert np.all(scale > 0)
