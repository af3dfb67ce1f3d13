"""Tests of gld/models/layers.py: activation slope, flow normalisation, network inputs,
depth head."""

import math

import jax.numpy as jnp
import numpy as np
import pytest

from gld.models import layers


def test_leaky_relu_has_slope_0_2_below_zero_and_identity_above():
    x = jnp.array([-2.0, -0.5, 0.0, 0.25, 3.0])
    np.testing.assert_allclose(layers.leaky_relu(x), [-0.4, -0.1, 0.0, 0.25, 3.0], rtol=1e-6)


def test_normalise_flow_divides_x_by_width_and_y_by_height():
    # H = 3, W = 4: a flow of (8, 6) pixels is 2 widths across and 2 heights down.
    flow = jnp.broadcast_to(jnp.array([8.0, 6.0]), (2, 3, 4, 2))
    np.testing.assert_allclose(layers.normalise_flow(flow), 2.0)
    # Unbatched [H, W, 2] uses the same two trailing spatial axes.
    single = jnp.stack([jnp.full((5, 10), -5.0), jnp.full((5, 10), 1.0)], axis=-1)
    normalised = layers.normalise_flow(single)
    np.testing.assert_allclose(normalised[..., 0], -0.5)
    np.testing.assert_allclose(normalised[..., 1], 0.2)
    assert layers.normalise_flow(flow.astype(jnp.float16)).dtype == jnp.float16


def test_network_inputs_stack_images_then_normalised_flow():
    rng = np.random.default_rng(0)
    image1 = rng.uniform(-0.5, 0.5, (2, 3, 4, 3)).astype(np.float32)
    image2 = rng.uniform(-0.5, 0.5, (2, 3, 4, 3)).astype(np.float32)
    flow = rng.normal(size=(2, 3, 4, 2)).astype(np.float32)
    inputs = np.asarray(layers.network_inputs(image1, image2, flow))
    assert inputs.shape == (2, 3, 4, 8)
    np.testing.assert_array_equal(inputs[..., 0:3], image1)
    np.testing.assert_array_equal(inputs[..., 3:6], image2)
    np.testing.assert_allclose(inputs[..., 6], flow[..., 0] / 4.0, rtol=1e-6)
    np.testing.assert_allclose(inputs[..., 7], flow[..., 1] / 3.0, rtol=1e-6)


def test_positive_inv_depth_starts_at_the_initial_value_and_stays_above_the_floor():
    # softplus(0 + log(expm1(c))) = c exactly; the floor is added on top.
    zero = layers.positive_inv_depth(jnp.zeros(3))
    np.testing.assert_allclose(zero, layers.INITIAL_INV_DEPTH + layers.MIN_INV_DEPTH, rtol=1e-6)
    # Very negative logits saturate at the floor; very positive ones grow linearly.
    low = layers.positive_inv_depth(jnp.array([-100.0]))
    np.testing.assert_allclose(low, layers.MIN_INV_DEPTH, rtol=1e-4)
    high = layers.positive_inv_depth(jnp.array([50.0]))
    expected_high = 50.0 + math.log(math.expm1(layers.INITIAL_INV_DEPTH)) + layers.MIN_INV_DEPTH
    np.testing.assert_allclose(high, expected_high, rtol=1e-6)
    # Monotonic increasing.
    ramp = np.asarray(layers.positive_inv_depth(jnp.linspace(-10.0, 10.0, 101)))
    assert np.all(np.diff(ramp) > 0)


@pytest.mark.parametrize("shape", [(2, 3, 4, 1), (2, 3, 4)])
def test_depth_outputs_are_positive_reciprocals(shape):
    logits = jnp.asarray(np.random.default_rng(1).normal(scale=5.0, size=shape), jnp.float32)
    outputs = layers.depth_outputs(logits)
    assert set(outputs) == {"inv_depth", "depth"}
    assert outputs["inv_depth"].shape == (2, 3, 4) and outputs["depth"].shape == (2, 3, 4)
    assert bool(jnp.all(outputs["inv_depth"] >= layers.MIN_INV_DEPTH))
    np.testing.assert_allclose(outputs["inv_depth"] * outputs["depth"], 1.0, rtol=1e-6)
    # The channel axis is dropped, not reduced: same values with or without it.
    np.testing.assert_allclose(
        outputs["inv_depth"], layers.positive_inv_depth(logits.reshape(2, 3, 4)), rtol=1e-6
    )
    # A zero logit means the initial inverse depth, i.e. a depth of ~10.
    initial = layers.depth_outputs(jnp.zeros((1, 1, 1, 1)))
    np.testing.assert_allclose(initial["depth"], 1.0 / (0.1 + layers.MIN_INV_DEPTH), rtol=1e-6)
