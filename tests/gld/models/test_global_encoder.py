"""Tests of gld/models/global_encoder.py: the conv stack, its global average pooling, its checks."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax import lax

from gld.models import layers
from gld.models.global_encoder import GlobalEncoder

# Three hidden layers keep compile times low; strides cover both 2 and 1.
CHANNELS = (4, 6, 5)
STRIDES = (2, 2, 1)


def _init(encoder, inputs, seed=0):
    # The 'rbg' generator compiles several times faster than threefry on CPU.
    return jax.jit(encoder.init)(jax.random.key(seed, impl="rbg"), inputs)


def _inputs(batch=2, height=16, width=12, channels=8, seed=0):
    rng = np.random.default_rng(seed)
    return jnp.asarray(rng.normal(size=(batch, height, width, channels)), jnp.float32)


def _reference(params, inputs, strides, instance_norm=False):
    """The documented encoder written out: SAME convs, LeakyReLU after each hidden one
    (after standardising each channel over the image, scaled and shifted, with
    `instance_norm`), a conv to global_dim, the spatial mean."""

    def conv(features, layer, stride):
        out = lax.conv_general_dilated(
            features,
            layer["kernel"],
            (stride, stride),
            "SAME",
            dimension_numbers=("NHWC", "HWIO", "NHWC"),
            precision=lax.Precision.HIGHEST,
        )
        return out + layer["bias"]

    features = inputs
    for index, stride in enumerate(strides):
        pre = conv(features, params[f"conv{index}"], stride)
        if instance_norm:
            norm = params[f"norm{index}"]
            mean = pre.mean(axis=(1, 2), keepdims=True)
            variance = pre.var(axis=(1, 2), keepdims=True)
            pre = (pre - mean) / jnp.sqrt(variance + 1e-6) * norm["scale"] + norm["bias"]
        features = jnp.where(pre > 0, pre, layers.NEGATIVE_SLOPE * pre)
    final = conv(features, params["to_global"], 1)
    return final, jnp.mean(final, axis=(1, 2))


@pytest.fixture(scope="module")
def small_encoder():
    """A 3-hidden-layer encoder with global_dim 3, its variables and a batch of 3."""
    encoder = GlobalEncoder(channels=CHANNELS, strides=STRIDES, global_dim=3)
    inputs = _inputs(batch=3)
    return encoder, _init(encoder, inputs), inputs


def test_output_equals_the_spatial_mean_of_the_documented_conv_stack(small_encoder):
    encoder, variables, inputs = small_encoder
    params = variables["params"]
    assert [params[f"conv{i}"]["kernel"].shape for i in range(3)] == [
        (3, 3, 8, 4),
        (3, 3, 4, 6),
        (3, 3, 6, 5),
    ]
    assert params["to_global"]["kernel"].shape == (3, 3, 5, 3)
    global_params, state = encoder.apply(variables, inputs, capture_intermediates=True)
    final_map, expected = _reference(params, inputs, STRIDES)
    assert global_params.shape == (3, 3)
    np.testing.assert_allclose(global_params, expected, rtol=1e-4, atol=1e-6)
    # Two stride-2 layers: 16x12 -> 4x3 before pooling, and the module pooled that map.
    to_global = state["intermediates"]["to_global"]["__call__"][0]
    assert to_global.shape == final_map.shape == (3, 4, 3, 3)
    np.testing.assert_allclose(global_params, to_global.mean(axis=(1, 2)), rtol=1e-6, atol=1e-7)


def test_examples_are_encoded_independently(small_encoder):
    encoder, variables, inputs = small_encoder
    together = encoder.apply(variables, inputs)
    alone = encoder.apply(variables, inputs[1:2])
    np.testing.assert_allclose(alone[0], together[1], rtol=1e-5, atol=1e-7)
    assert not np.allclose(together[0], together[1], rtol=1e-3)


def _shuffle_pixels(inputs, seed=3):
    batch, height, width, channels = inputs.shape
    order = np.random.default_rng(seed).permutation(height * width)
    flat = inputs.reshape(batch, height * width, channels)
    return flat[:, order].reshape(inputs.shape)


def test_pointwise_encoder_is_invariant_to_shuffling_pixels(small_encoder):
    # With 1x1 kernels and stride 1 every layer acts per pixel, so the spatial mean
    # makes the output depend only on the set of pixels, not on where they are.
    encoder = GlobalEncoder(channels=(4, 4), strides=(1, 1), kernel_size=1)
    inputs = _inputs(batch=1, height=6, width=5)
    variables = _init(encoder, inputs, 2)
    original = encoder.apply(variables, inputs)
    shuffled = encoder.apply(variables, _shuffle_pixels(inputs))
    np.testing.assert_allclose(shuffled, original, rtol=1e-5, atol=1e-7)
    # It does depend on the pixel values.
    changed = inputs.at[0, 2, 3].add(5.0)
    assert not np.allclose(encoder.apply(variables, changed), original)
    # A 3x3 encoder sees neighbourhoods, so a shuffle changes its output.
    spatial, spatial_variables, spatial_inputs = small_encoder
    assert not np.allclose(
        spatial.apply(spatial_variables, _shuffle_pixels(spatial_inputs)),
        spatial.apply(spatial_variables, spatial_inputs),
        rtol=1e-3,
    )


def test_paper_defaults_shrink_by_16_and_end_in_six_parameters():
    encoder = GlobalEncoder()
    image = jax.ShapeDtypeStruct((1, 192, 256, 8), jnp.float32)
    variables = jax.eval_shape(encoder.init, jax.random.key(0), image)
    kernels = [variables["params"][f"conv{i}"]["kernel"].shape for i in range(5)]
    assert kernels == [
        (3, 3, 8, 16),
        (3, 3, 16, 32),
        (3, 3, 32, 64),
        (3, 3, 64, 128),
        (3, 3, 128, 256),
    ]
    assert variables["params"]["to_global"]["kernel"].shape == (3, 3, 256, 6)
    _, state = jax.eval_shape(
        lambda v, x: encoder.apply(v, x, capture_intermediates=True), variables, image
    )
    assert state["intermediates"]["to_global"]["__call__"][0].shape == (1, 12, 16, 6)


@pytest.mark.parametrize("channels, strides", [((4, 4), (2,)), ((4,), (2, 1)), ((4, 4, 4), (2, 2))])
def test_channels_and_strides_of_different_lengths_are_rejected(channels, strides):
    encoder = GlobalEncoder(channels=channels, strides=strides)
    with pytest.raises(ValueError, match=r"channels .* and strides .* differ in length"):
        encoder.init(jax.random.key(0), _inputs(batch=1, height=8, width=8))


def test_instance_norm_standardises_each_channel_per_example_before_the_activation():
    encoder = GlobalEncoder(channels=CHANNELS, strides=STRIDES, global_dim=3, norm="instance")
    inputs = _inputs(batch=3)
    variables = _init(encoder, inputs)
    params = variables["params"]
    assert set(params["norm0"]) == {"scale", "bias"}
    # Non-trivial scales and offsets, so that where they act shows in the output.
    rng = np.random.default_rng(5)
    for index in range(len(CHANNELS)):
        for name in ("scale", "bias"):
            shape = params[f"norm{index}"][name].shape
            params[f"norm{index}"][name] = jnp.asarray(rng.normal(size=shape), jnp.float32)
    _, expected = _reference(params, inputs, STRIDES, instance_norm=True)
    np.testing.assert_allclose(
        encoder.apply({"params": params}, inputs), expected, rtol=1e-3, atol=1e-5
    )
    variables = _init(encoder, inputs)
    _, state = encoder.apply(variables, inputs, capture_intermediates=True)
    for index in range(len(CHANNELS)):
        normalised = np.asarray(state["intermediates"][f"norm{index}"]["__call__"][0])
        # Unit scale and zero offset at initialisation: each channel of each example has
        # zero mean and unit variance over the image.
        np.testing.assert_allclose(normalised.mean(axis=(1, 2)), 0.0, atol=1e-4)
        np.testing.assert_allclose(normalised.std(axis=(1, 2)), 1.0, rtol=1e-2)
    # Each example is normalised alone, so a batch mate does not change its output.
    together = encoder.apply(variables, inputs)
    np.testing.assert_allclose(
        encoder.apply(variables, inputs[1:2])[0], together[1], rtol=1e-4, atol=1e-6
    )


def test_instance_norm_makes_the_encoder_blind_to_the_inputs_contrast():
    # conv(c x) + b = c conv(x) + b, and standardising over the image removes both c > 0
    # and b: only the normalised encoder ignores a change of contrast.
    inputs = _inputs(batch=2)
    for norm, blind in (("instance", True), ("none", False)):
        encoder = GlobalEncoder(channels=CHANNELS, strides=STRIDES, global_dim=3, norm=norm)
        variables = _init(encoder, inputs)
        original = encoder.apply(variables, inputs)
        contrast = encoder.apply(variables, inputs * 4.0)
        assert np.allclose(contrast, original, rtol=1e-3, atol=1e-5) == blind, norm


def test_instance_norm_refuses_a_map_it_would_zero():
    encoder = GlobalEncoder(channels=(4, 4), strides=(2, 2), norm="instance")
    with pytest.raises(ValueError, match="conv1 of the global encoder outputs a 1x1 map"):
        encoder.init(jax.random.key(0), _inputs(batch=1, height=4, width=4))


def test_an_unknown_norm_is_named():
    encoder = GlobalEncoder(channels=CHANNELS, strides=STRIDES, norm="batch")
    with pytest.raises(ValueError, match=r"norm must be one of \('none', 'instance'\)"):
        encoder.init(jax.random.key(0), _inputs(batch=1))
