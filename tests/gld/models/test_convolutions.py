"""The conv of the baselines and the flow network (`gld.models.layers.Conv`): flax's, with
maps smaller than the kernel convolved as patches
(`gld.models.convolutions.conv_general_dilated`), and the patches themselves."""

from __future__ import annotations

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from gld.models import convolutions, layers

# (input [B, H, W, C], kernel size, strides, padding): maps smaller than the kernel (the
# module's patches), larger maps strided, with explicit and 'VALID' padding (lax's there).
CASES = [
    ((2, 4, 4, 6), 5, 1, "SAME"),
    ((2, 1, 1, 5), 3, 1, "SAME"),
    ((1, 2, 3, 4), 3, 2, "SAME"),
    ((2, 8, 6, 3), 3, 2, "SAME"),
    ((2, 5, 7, 3), 3, 1, ((2, 0), (1, 3))),
    ((1, 6, 6, 4), 3, 1, "VALID"),
    ((2, 16, 12, 3), 3, 1, "SAME"),
]


@pytest.mark.parametrize("shape, kernel_size, stride, padding", CASES)
def test_the_conv_gives_flaxs_values_and_gradients(shape, kernel_size, stride, padding):
    inputs = jnp.asarray(np.random.default_rng(0).normal(size=shape), jnp.float32)
    modules = [
        conv(7, (kernel_size, kernel_size), strides=stride, padding=padding)
        for conv in (layers.Conv, nn.Conv)
    ]
    variables = modules[1].init(jax.random.key(0), inputs)
    # The same parameters, by the same names: a checkpoint of either loads in the other.
    assert jax.tree.structure(modules[0].init(jax.random.key(0), inputs)) == jax.tree.structure(
        variables
    )

    def loss(module, variables, inputs):
        return jnp.sum(jnp.sin(module.apply(variables, inputs)))

    ours, flax_s = (
        (m.apply(variables, inputs), jax.grad(loss, argnums=(1, 2))(m, variables, inputs))
        for m in modules
    )
    np.testing.assert_allclose(ours[0], flax_s[0], rtol=1e-5, atol=1e-5)
    for got, want in zip(jax.tree.leaves(ours[1]), jax.tree.leaves(flax_s[1]), strict=True):
        np.testing.assert_allclose(got, want, rtol=1e-4, atol=1e-4)


@pytest.mark.parametrize("shape, kernel_size, stride, padding", CASES)
def test_the_patches_give_laxs_values_and_gradients(shape, kernel_size, stride, padding):
    """On any map, small or not: the strides, paddings and dropped taps are the patches'."""
    rng = np.random.default_rng(0)
    inputs = jnp.asarray(rng.normal(size=shape), jnp.float32)
    kernel = jnp.asarray(rng.normal(size=(kernel_size, kernel_size, shape[-1], 7)), jnp.float32)
    strides = (stride, stride)
    if isinstance(padding, str):
        padding = jax.lax.padtype_to_pads(shape[1:3], kernel.shape[:2], strides, padding)

    def patches(inputs, kernel):
        return convolutions.patches_conv(inputs, kernel, strides, tuple(map(tuple, padding)))

    def lax_s(inputs, kernel):
        return jax.lax.conv_general_dilated(
            inputs, kernel, strides, padding, dimension_numbers=convolutions.DIMENSION_NUMBERS
        )

    np.testing.assert_allclose(patches(inputs, kernel), lax_s(inputs, kernel), rtol=1e-5, atol=1e-5)
    grads = [
        jax.grad(lambda i, k, f=f: jnp.sum(jnp.sin(f(i, k))), argnums=(0, 1))(inputs, kernel)
        for f in (patches, lax_s)
    ]
    for got, want in zip(*grads, strict=True):
        np.testing.assert_allclose(got, want, rtol=1e-4, atol=1e-4)


def test_maps_smaller_than_the_kernel_and_only_they_are_convolved_as_patches(monkeypatch):
    calls = []
    patches_conv = convolutions.patches_conv
    monkeypatch.setattr(
        convolutions, "patches_conv", lambda *a, **k: calls.append(a[0].shape) or patches_conv(*a)
    )
    for shape in [(1, 1, 1, 2), (1, 2, 40, 2), (1, 40, 2, 2), (1, 3, 3, 2), (1, 8, 8, 2)]:
        layers.Conv(3, (3, 3)).init(jax.random.key(0), jnp.zeros(shape))
    # Maps smaller than the 3x3 kernel on a side; not one as large as it, nor a larger one.
    assert calls == [(1, 1, 1, 2), (1, 2, 40, 2), (1, 40, 2, 2)]


def test_a_conv_of_a_tiny_map_reads_only_the_taps_that_reach_it():
    """A 3x3 conv of a 1x1 map is its centre tap: the other taps read padding alone."""
    inputs = jnp.arange(4.0).reshape(1, 1, 1, 4)
    kernel = jnp.asarray(np.random.default_rng(1).normal(size=(3, 3, 4, 2)), jnp.float32)
    out = convolutions.patches_conv(inputs, kernel, (1, 1), ((1, 1), (1, 1)))
    np.testing.assert_allclose(out[0, 0, 0], inputs[0, 0, 0] @ kernel[1, 1], rtol=1e-6)
    jaxpr = str(
        jax.make_jaxpr(convolutions.patches_conv, static_argnums=(2, 3))(
            inputs, kernel, (1, 1), ((1, 1), (1, 1))
        )
    )
    assert "f32[4,2]" in jaxpr and "f32[36,2]" not in jaxpr


def test_a_padding_no_output_reads_the_image_through_gives_laxs_zeros():
    inputs, kernel = jnp.ones((1, 1, 4, 3)), jnp.ones((3, 3, 3, 4))
    padding = ((3, 3), (1, 1))
    out = convolutions.patches_conv(inputs, kernel, (7, 1), padding)
    want = jax.lax.conv_general_dilated(
        inputs, kernel, (7, 1), padding, dimension_numbers=convolutions.DIMENSION_NUMBERS
    )
    assert out.shape == want.shape == (1, 1, 4, 4)
    np.testing.assert_array_equal(out, want)
