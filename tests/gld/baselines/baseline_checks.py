"""Shared checks of the learned baselines: output shapes and a few training steps.

A plain module (not a conftest.py, whose module name would shadow tests/conftest.py).
"""

import jax
import jax.numpy as jnp
import numpy as np
import optax

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


def train_tiny(model, *, height=32, width=32, steps=25, learning_rate=1e-3):
    """Adam on a sparse L1 inverse-depth loss over one tiny batch.

    Returns:
      the losses of every step (each of the parameters before that step's update), the
      outputs of the trained model in evaluation mode (`train=False`), and its variables.
    """
    image1, image2, flow, target, mask = tiny_batch(2, height, width)
    variables = jax.jit(model.init)(jax.random.key(0, impl=INIT_KEY_IMPL), image1, image2, flow)
    params = variables["params"]
    batch_stats = variables.get("batch_stats")
    optimizer = optax.adam(learning_rate)
    opt_state = optimizer.init(params)

    def loss_fn(params, batch_stats, dropout_key):
        rngs = {"dropout": dropout_key}
        if batch_stats is not None:
            outputs, updates = model.apply(
                {"params": params, "batch_stats": batch_stats},
                image1,
                image2,
                flow,
                train=True,
                rngs=rngs,
                mutable=["batch_stats"],
            )
            batch_stats = updates["batch_stats"]
        else:
            outputs = model.apply({"params": params}, image1, image2, flow, train=True, rngs=rngs)
        error = jnp.abs(outputs["inv_depth"] - target)
        return jnp.sum(error * mask) / jnp.sum(mask), batch_stats

    @jax.jit
    def step(params, batch_stats, opt_state, dropout_key):
        (loss, batch_stats), grads = jax.value_and_grad(loss_fn, has_aux=True)(
            params, batch_stats, dropout_key
        )
        updates, opt_state = optimizer.update(grads, opt_state, params)
        return optax.apply_updates(params, updates), batch_stats, opt_state, loss

    losses = []
    for index in range(steps):
        dropout_key = jax.random.key(index, impl=INIT_KEY_IMPL)
        params, batch_stats, opt_state, loss = step(params, batch_stats, opt_state, dropout_key)
        losses.append(float(loss))
    assert np.all(np.isfinite(losses)), losses

    trained = {"params": params}
    if batch_stats is not None:
        trained["batch_stats"] = batch_stats
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
