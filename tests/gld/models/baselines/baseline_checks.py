"""Shared checks of the learned baselines: output shapes, numpy versions of their
output head, and learning a problem with a known answer.

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


def sideways_planes(batch_size: int, height: int, width: int, seed: int):
    """A problem with a known answer: fronto-parallel planes at random inverse depths in
    [0.1, 0.5], seen by a camera of focal length `width` pixels moving sideways by one
    unit, so that the flow is (width * inverse depth, 0) everywhere. The images are
    noise; ~10% of the pixels are supervised.

    Returns:
      the batch (the example contract's keys the trainer reads) and the true inverse
      depth [B, H, W].
    """
    rng = np.random.default_rng(seed)
    inv_depth = np.broadcast_to(
        rng.uniform(0.1, 0.5, (batch_size, 1, 1)), (batch_size, height, width)
    ).astype(np.float32)
    flow = np.stack([width * inv_depth, np.zeros_like(inv_depth)], axis=-1)
    batch = {
        "image1": rng.uniform(-0.5, 0.5, (batch_size, height, width, 3)).astype(np.float32),
        "image2": rng.uniform(-0.5, 0.5, (batch_size, height, width, 3)).astype(np.float32),
        "flow": flow,
        "depth": 1.0 / inv_depth,
        "sparse_mask": rng.uniform(size=(batch_size, height, width)) < 0.1,
    }
    return batch, inv_depth


def train_tiny(model, *, steps, learning_rate=1e-3, height=32, width=32, batch_size=4):
    """The trainer's step (`train.make_train_step`, Adam) on `sideways_planes`, a fresh
    batch every step, with only the sparse L1 inverse-depth term (smoothness weight 0);
    multi-scale models get it at every scale, as in training.

    Returns:
      the loss of every step (on a batch the model had not seen), the trained model's
      outputs in evaluation mode (`train=False`) on 16 other pairs, their true inverse
      depth, and the trained variables.
    """
    first, _ = sideways_planes(batch_size, height, width, seed=0)
    variables = jax.jit(model.init)(
        jax.random.key(0, impl=INIT_KEY_IMPL), first["image1"], first["image2"], first["flow"]
    )
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
        batch, _ = sideways_planes(batch_size, height, width, seed=index)
        dropout_key = jax.random.key(index, impl=INIT_KEY_IMPL)
        state, step_metrics = step(state, batch, dropout_key)
        losses.append(float(step_metrics["loss"]))
    assert np.all(np.isfinite(losses)), losses
    assert int(state.step) == steps

    trained = state.variables()
    held_out, held_out_inv_depth = sideways_planes(16, height, width, seed=steps + 1)
    inputs = [held_out[key] for key in ("image1", "image2", "flow")]
    outputs = jax.jit(lambda variables: model.apply(variables, *inputs))(trained)
    return np.asarray(losses), jax.tree.map(np.asarray, outputs), held_out_inv_depth, trained


def check_learned(losses, outputs, inv_depth):
    """The common assertions on `train_tiny`'s results: the loss of unseen batches
    falls to under half its start (mean of the last 10 steps against the first 10), and
    on held-out pairs the prediction is within half the error of the best constant
    (whose error is the mean distance to the median): the model reads the depth from
    the flow."""
    assert losses[-10:].mean() < 0.5 * losses[:10].mean(), losses
    error = np.abs(outputs["inv_depth"] - inv_depth).mean()
    best_constant = np.abs(inv_depth - np.median(inv_depth)).mean()
    assert error < 0.5 * best_constant, (error, best_constant)
    assert np.all(outputs["inv_depth"] > 0)
    np.testing.assert_allclose(outputs["depth"] * outputs["inv_depth"], 1.0, rtol=1e-5)
    for scale in outputs.get("inv_depth_pyramid", ()):
        assert np.all(scale > 0)


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


def drawn_variables(model, height, width, seed=0, batch_size=2):
    """Variables of `model`'s structure drawn with numpy: weights N(0, 1/fan-in), every
    vector (biases, norm scales and offsets) N(0, 0.1^2) but running variances in [0.5,
    1.5], so that every parameter matters (a zero bias would hide a misplaced one)."""
    image = jax.ShapeDtypeStruct((batch_size, height, width, 3), jnp.float32)
    flow = jax.ShapeDtypeStruct((batch_size, height, width, 2), jnp.float32)
    shapes = jax.eval_shape(model.init, jax.random.key(0), image, image, flow)
    rng = np.random.default_rng(seed)

    def draw(path, leaf):
        if jax.tree_util.keystr(path[-1:]) == "['var']":
            return rng.uniform(0.5, 1.5, leaf.shape).astype(leaf.dtype)
        if len(leaf.shape) < 2:
            return rng.normal(0.0, 0.1, leaf.shape).astype(leaf.dtype)
        fan_in = int(np.prod(leaf.shape[:-1]))
        return rng.normal(0.0, fan_in**-0.5, leaf.shape).astype(leaf.dtype)

    return jax.tree_util.tree_map_with_path(draw, shapes)


def upsample_bilinear(maps, height, width):
    """[B, h, w] -> [B, height, width] by bilinear interpolation between pixel centres
    (output pixel i samples input coordinate (i + 0.5) * h / height - 0.5, clamped to
    the image), written out in numpy."""
    maps = np.asarray(maps, np.float64)

    def weights(out_size, in_size):
        source = np.clip((np.arange(out_size) + 0.5) * in_size / out_size - 0.5, 0, in_size - 1)
        low = np.floor(source).astype(int)
        high = np.minimum(low + 1, in_size - 1)
        matrix = np.zeros((out_size, in_size))
        matrix[np.arange(out_size), low] += 1.0 - (source - low)
        matrix[np.arange(out_size), high] += source - low
        return matrix

    rows, cols = weights(height, maps.shape[1]), weights(width, maps.shape[2])
    return np.einsum("ih,bhw,jw->bij", rows, maps, cols)


def capturing(model, **kwargs):
    """A jit-compiled `(variables, image1, image2, flow) -> (outputs, {layer name: its
    output})` of `model.apply`, numpy out; the layers are the model's direct children;
    `kwargs` go to `apply` (train, mutable)."""

    @jax.jit
    def run(variables, image1, image2, flow):
        outputs, state = model.apply(
            variables, image1, image2, flow, capture_intermediates=True, **kwargs
        )
        captured = {
            name: layer["__call__"][0]
            for name, layer in state["intermediates"].items()
            if "__call__" in layer
        }
        return outputs, captured

    return lambda *arguments: jax.tree.map(np.asarray, run(*arguments))
