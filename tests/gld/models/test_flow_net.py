"""The flow network's pieces: warping, the cost volume, upsampling, shapes and checks."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from gld.models import flow_net

# A small network: its parameters initialise and compile in seconds.
SMALL = dict(
    feature_channels=(4, 6, 8, 8),
    estimator_channels=(8, 6),
    context_channels=(6, 4),
    max_displacement=2,
)


@pytest.fixture(scope="module")
def small_net():
    model = flow_net.FlowNet(**SMALL)
    return model, {"params": flow_net.init_params(model, seed=0)}


@pytest.mark.parametrize("height, width", [(48, 64), (96, 128), (192, 256)])
def test_outputs_have_the_input_resolution_and_one_estimate_per_level(small_net, height, width):
    model, variables = small_net
    images = jax.random.uniform(jax.random.key(1), (2, 2, height, width, 3)) - 0.5
    outputs = jax.jit(model.apply)(variables, images[0], images[1])
    assert outputs["flow"].shape == (2, height, width, 2)
    # levels 4, 3, 2 (finest_level 2 by default), coarsest first
    assert [level.shape for level in outputs["flow_pyramid"]] == [
        (2, height // 16, width // 16, 2),
        (2, height // 8, width // 8, 2),
        (2, height // 4, width // 4, 2),
    ]
    assert np.all(np.isfinite(outputs["flow"]))
    # every estimate is in pixels of the input: the output is the finest one resized
    resized = jax.image.resize(outputs["flow_pyramid"][-1], (2, height, width, 2), "bilinear")
    np.testing.assert_allclose(outputs["flow"], resized, rtol=1e-5, atol=1e-5)


def test_default_network_is_compact_and_estimates_down_to_half_resolution():
    default = flow_net.FlowNet()
    images = jax.ShapeDtypeStruct((1, 96, 128, 3), jnp.float32)
    shapes = jax.eval_shape(default.init, jax.random.key(0), images, images)
    assert 100_000 < flow_net.parameter_count(shapes["params"]) < 500_000
    half = flow_net.FlowNet(**SMALL, finest_level=1)
    params = flow_net.init_params(half, seed=0)
    images = jnp.zeros((1, 48, 64, 3))
    outputs = jax.jit(half.apply)({"params": params}, images, images)
    assert outputs["flow_pyramid"][-1].shape == (1, 24, 32, 2)
    assert outputs["flow"].shape == (1, 48, 64, 2)


def test_images_not_divisible_by_the_pyramid_are_refused_naming_the_size(small_net):
    model, variables = small_net
    images = jnp.zeros((1, 40, 64, 3))
    with pytest.raises(ValueError, match=r"64x40 .* not divisible by 16"):
        model.apply(variables, images, images)
    with pytest.raises(ValueError, match="same shape"):
        model.apply(variables, jnp.zeros((1, 48, 64, 3)), jnp.zeros((1, 48, 48, 3)))
    with pytest.raises(ValueError, match=r"\[B, H, W, 3\]"):
        model.apply(variables, jnp.zeros((1, 48, 64, 1)), jnp.zeros((1, 48, 64, 1)))


@pytest.mark.parametrize(
    "options, message",
    [
        (dict(finest_level=5), "finest_level must be in"),
        (dict(feature_channels=()), "feature_channels"),
        (dict(estimator_channels=(8, 0)), "estimator_channels"),
        (dict(max_displacement=0), "max_displacement"),
    ],
)
def test_bad_architectures_are_refused(options, message):
    model = flow_net.FlowNet(**{**SMALL, **options})
    with pytest.raises(ValueError, match=message):
        flow_net.init_params(model, seed=0)


def test_warping_by_a_constant_flow_reproduces_the_shifted_image():
    rng = np.random.default_rng(0)
    image1 = rng.uniform(size=(1, 20, 24, 3)).astype(np.float32)
    shift_u, shift_v = 3, -2
    # image2(p) = image1(p - shift): pixel p of image 1 sits at p + shift in image 2
    image2 = np.roll(image1, (shift_v, shift_u), axis=(1, 2))
    flow = np.broadcast_to(np.float32([shift_u, shift_v]), (1, 20, 24, 2))
    warped = np.asarray(flow_net.warp(jnp.asarray(image2), jnp.asarray(flow)))
    np.testing.assert_allclose(warped[:, 2:-2, :-3], image1[:, 2:-2, :-3], atol=1e-6)
    # lookups beyond the border see zeros (the right 3 columns land outside image 2)
    np.testing.assert_allclose(warped[:, :, -3:], 0.0)


def test_warping_by_a_fractional_flow_interpolates_bilinearly_and_is_differentiable():
    v, u = np.mgrid[0:10, 0:12].astype(np.float32)
    ramp = (2.0 * u + 3.0 * v)[None, ..., None]
    flow = np.broadcast_to(np.float32([0.25, 0.5]), (1, 10, 12, 2))
    warped = np.asarray(flow_net.warp(jnp.asarray(ramp), jnp.asarray(flow)))
    # a linear image is reproduced exactly by bilinear interpolation: + 2 * 0.25 + 3 * 0.5
    np.testing.assert_allclose(warped[0, :-1, :-1, 0], ramp[0, :-1, :-1, 0] + 2.0, atol=1e-5)
    # d warped / d flow is the image gradient (2, 3) inside
    grad = jax.grad(lambda f: jnp.sum(flow_net.warp(jnp.asarray(ramp), f)[:, 1:-2, 1:-2]))(
        jnp.asarray(flow)
    )
    np.testing.assert_allclose(grad[0, 1:-2, 1:-2], np.broadcast_to([2.0, 3.0], (7, 9, 2)))


def test_correlation_of_identical_features_peaks_at_zero_displacement():
    features = jax.random.normal(jax.random.key(0), (2, 9, 11, 16))
    # unit vectors: by Cauchy-Schwarz a pixel matches itself best
    features = flow_net.unit_features(features)
    cost = np.asarray(flow_net.correlation(features, features, max_displacement=3))
    assert cost.shape == (2, 9, 11, 49)
    assert np.all(np.argmax(cost, axis=-1) == 24)  # (2d + 1)**2 // 2
    # the centre channel is each unit vector's square: 1
    np.testing.assert_allclose(cost[..., 24], 1.0, rtol=1e-5)


def test_correlation_peaks_at_the_displacement_between_the_maps():
    features1 = jax.random.normal(jax.random.key(0), (1, 12, 14, 16))
    features1 = flow_net.unit_features(features1)
    du, dv = 2, -1
    # features2 at p + (du, dv) equals features1 at p
    features2 = jnp.roll(features1, (dv, du), axis=(1, 2))
    cost = np.asarray(flow_net.correlation(features1, features2, max_displacement=3))
    channel = (dv + 3) * 7 + (du + 3)
    assert np.all(np.argmax(cost[0, 3:-3, 3:-3], axis=-1) == channel)


def test_upsampling_scales_a_constant_flow_by_the_factor():
    flow = jnp.broadcast_to(jnp.float32([1.5, -0.5]), (1, 3, 4, 2))
    upsampled = np.asarray(flow_net.upsample_flow(flow, 4))
    assert upsampled.shape == (1, 12, 16, 2)
    np.testing.assert_allclose(upsampled, np.broadcast_to([6.0, -2.0], (1, 12, 16, 2)), rtol=1e-6)
