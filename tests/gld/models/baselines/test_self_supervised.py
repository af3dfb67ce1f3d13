import dataclasses

import baseline_checks
import cv2
import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

from gld import geometry
from gld.losses import photometric
from gld.models import baselines
from gld.models.baselines.self_supervised import (
    SelfSupervised,
    SelfSupervisedFlow,
    rotation_from_axis_angle,
)

HEIGHT, WIDTH = 32, 32
# Compiled whole: on CPU much faster than op-by-op dispatch of the same functions.
self_supervised_loss = jax.jit(photometric.self_supervised_loss)


def init(model, image1, image2, flow):
    key = jax.random.key(0, impl=baseline_checks.INIT_KEY_IMPL)
    return jax.jit(model.init)(key, image1, image2, flow)


def random_inputs(seed=0, batch_size=2):
    image1, image2, flow, _, _ = baseline_checks.tiny_batch(batch_size, HEIGHT, WIDTH, seed)
    return image1, image2, flow


def test_axis_angle_matches_gld_geometry_and_is_smooth_at_zero():
    to_matrix = jax.jit(rotation_from_axis_angle)
    axis_angle = np.random.default_rng(0).normal(0.0, 0.7, (5, 3)).astype(np.float32)
    np.testing.assert_allclose(
        to_matrix(axis_angle),
        geometry.rotation_matrix(axis_angle),
        atol=1e-5,
    )
    # Below the Taylor threshold too (a 1e-5 rad rotation).
    tiny = np.asarray([1e-5, -2e-5, 5e-6], np.float32)
    np.testing.assert_allclose(to_matrix(tiny), geometry.rotation_matrix(tiny), atol=1e-7)
    np.testing.assert_array_equal(to_matrix(np.zeros(3, np.float32)), np.eye(3))
    # Just above it, where 1 - cos(a) would cancel in float32: the K^2 / 2 term alone
    # makes R[0, 1] (no K term there for an axis in the x-y plane).
    small = np.asarray([2e-4, 2e-4, 0.0])
    expected = geometry.rotation_matrix(small)[0, 1]  # float64
    np.testing.assert_allclose(to_matrix(small.astype(np.float32))[0, 1], expected, rtol=1e-3)
    # d R / d axis-angle at zero is the cross-product matrix: d R[1, 0] / d z = 1.
    jacobian = jax.jit(jax.jacobian(rotation_from_axis_angle))(jnp.zeros(3))
    assert np.all(np.isfinite(jacobian))
    np.testing.assert_allclose(jacobian[1, 0], [0.0, 0.0, 1.0], atol=1e-7)
    np.testing.assert_allclose(jacobian[0, 1], [0.0, 0.0, -1.0], atol=1e-7)


# One model for the tests below (initialised once): with the flow input and a depth
# range other than the default, so that both are exercised.
MODEL = SelfSupervised(use_flow=True, min_depth=0.5, max_depth=20.0)
apply_model = jax.jit(MODEL.apply)


@pytest.fixture(scope="module")
def variables():
    return init(MODEL, *random_inputs())


def test_pose_convention_zero_head_is_identity_and_init_is_near_identity(variables):
    image1, image2, flow = random_inputs()
    outputs = apply_model(variables, image1, image2, flow)
    # monodepth2's 0.01 output scale: the initial pose is a small motion.
    assert np.abs(outputs["axis_angle"]).max() < 0.05
    assert 0 < np.abs(outputs["translation"]).max() < 0.05
    np.testing.assert_allclose(
        outputs["rotation"], geometry.rotation_matrix(np.asarray(outputs["axis_angle"])), atol=1e-6
    )

    params = jax.tree.map(lambda x: x, variables["params"])
    params["pose_net"]["pose"] = jax.tree.map(jnp.zeros_like, params["pose_net"]["pose"])
    zeroed = apply_model({"params": params}, image1, image2, flow)
    np.testing.assert_array_equal(zeroed["axis_angle"], 0.0)
    np.testing.assert_array_equal(zeroed["translation"], 0.0)
    np.testing.assert_array_equal(zeroed["rotation"], np.broadcast_to(np.eye(3), (2, 3, 3)))
    assert np.all(np.isfinite(zeroed["depth"]))


def test_depth_is_in_units_of_the_predicted_baseline(variables):
    image1, image2, flow = random_inputs()
    outputs = jax.tree.map(np.asarray, apply_model(variables, image1, image2, flow))
    network_depth = 1.0 / outputs["inv_depth_scales"][0]
    baseline = np.linalg.norm(outputs["translation"], axis=-1)
    assert 1e-4 < baseline.min()
    assert np.all((network_depth >= 0.5 - 1e-5) & (network_depth <= 20.0 + 1e-3))
    np.testing.assert_allclose(outputs["depth"], network_depth / baseline[:, None, None], rtol=1e-5)
    np.testing.assert_allclose(outputs["depth"] * outputs["inv_depth"], 1.0, rtol=1e-5)
    # With use_flow the flow reaches the depth network.
    shifted = apply_model(variables, image1, image2, flow + 5.0)
    assert not np.allclose(shifted["inv_depth_scales"][0], outputs["inv_depth_scales"][0])


def test_outputs_feed_the_self_supervised_loss(variables):
    batch = shifted_plane_pair()
    outputs = apply_model(variables, batch["image1"], batch["image2"], batch["flow"])
    loss, terms = self_supervised_loss(outputs, batch)
    assert np.isfinite(float(loss)) and float(loss) > 0
    assert 0 <= float(terms["auto_mask_fraction"]) <= 1
    # The model's 'depth' and 'translation' / ||translation|| warp exactly as the
    # network's own units do (the loss is free of the scale).
    translation = np.asarray(outputs["translation"])
    normalised = dict(
        outputs,
        inv_depth_scales=(outputs["inv_depth"],),
        translation=translation / np.linalg.norm(translation, axis=-1, keepdims=True),
    )
    network_units = dict(outputs, inv_depth_scales=outputs["inv_depth_scales"][:1])
    np.testing.assert_allclose(
        self_supervised_loss(normalised, batch)[1]["photometric"],
        self_supervised_loss(network_units, batch)[1]["photometric"],
        rtol=1e-4,
    )


def test_shapes_and_parameters():
    for use_flow in (False, True):
        outputs = baseline_checks.output_shapes(SelfSupervised(use_flow=use_flow), 192, 256)
        assert outputs["rotation"].shape == (2, 3, 3)
        assert outputs["axis_angle"].shape == outputs["translation"].shape == (2, 3)
        assert [s.shape for s in outputs["inv_depth_scales"]] == [
            (2, 192 // 2**s, 256 // 2**s) for s in range(4)
        ]
    # Odd sizes: ceil-halved encoder maps; the scales follow them.
    outputs = baseline_checks.output_shapes(SelfSupervised(num_scales=2), 20, 28)
    assert [s.shape for s in outputs["inv_depth_scales"]] == [(2, 20, 28), (2, 10, 14)]

    # The flow adds 2 input channels to the first conv of each network (7x7, 16 filters)
    # and to the depth network's full-resolution skip (3x3, 16 filters), nothing else.
    without_flow = baselines.parameter_count(SelfSupervised(), 192, 256)
    with_flow = baselines.parameter_count(SelfSupervised(use_flow=True), 192, 256)
    assert with_flow - without_flow == 2 * (7 * 7 * 2 * 16) + 3 * 3 * 2 * 16
    assert SelfSupervisedFlow().use_flow
    assert baselines.parameter_count(SelfSupervisedFlow(), 192, 256) == with_flow


def test_the_self_supervised_models_train_without_depth_labels_and_their_loss_is_no_option():
    from gld.runs.config import TrainConfig
    from gld.training import trainer

    for name, model_class in (
        ("struct2depth", SelfSupervised),
        ("struct2depth_flow", SelfSupervisedFlow),
    ):
        assert baselines.LEARNED[name] is model_class
        assert isinstance(TrainConfig(model=name).loss_weights(), photometric.SelfSupervisedWeights)
        keys = trainer.batch_keys(model_class())
        assert "depth" not in keys and {"intrinsics1", "intrinsics2"} <= set(keys)
    # A supervised model of the same signature reads the depth.
    assert "depth" in trainer.batch_keys(baselines.LEARNED["small_encdec"]())
    fields = {field.name for field in dataclasses.fields(SelfSupervised)}
    assert "LOSS" not in fields
    assert {"use_flow", "num_scales", "min_depth", "max_depth", "pose_scale"} <= fields


def shifted_plane_pair(batch_size=2, shift=2, seed=0):
    """Fronto-parallel planes at depth 4 seen by a camera translated along x: a constant
    `shift`-pixel flow. Smooth random textures, different per example."""
    rng = np.random.default_rng(seed)
    noise = rng.uniform(0.0, 1.0, (batch_size, HEIGHT, WIDTH + shift, 3)).astype(np.float32)
    canvas = np.stack([cv2.GaussianBlur(n, (0, 0), 1.5) for n in noise])
    canvas = (canvas - canvas.min()) / (canvas.max() - canvas.min()) - 0.5
    flow = np.zeros((batch_size, HEIGHT, WIDTH, 2), np.float32)
    flow[..., 0] = shift
    return {
        "image1": canvas[:, :, shift:],
        "image2": canvas[:, :, :WIDTH],
        "flow": flow,
        "intrinsics1": np.tile([1.0, 1.0, 0.5, 0.5], (batch_size, 1)).astype(np.float32),
        "intrinsics2": np.tile([1.0, 1.0, 0.5, 0.5], (batch_size, 1)).astype(np.float32),
    }


@pytest.mark.slow  # ~15 s of CPU on the 2-core machine, most of it compiling the step
def test_training_learns_the_correspondence(variables):
    """Adam on the model's parameters with the self-supervised loss alone (no depth
    labels): the loss falls and the predicted depth and pose reproject view 1 onto the
    true 2-pixel shift. (A single plane cannot separate the pose's rotation from its
    translation, so the depth itself is not checked here.)"""
    shift = 2
    batch = shifted_plane_pair(shift=shift)
    optimizer = optax.adam(1e-3)
    opt_state = optimizer.init(variables["params"])

    def loss_fn(params):
        outputs = MODEL.apply({"params": params}, batch["image1"], batch["image2"], batch["flow"])
        return photometric.self_supervised_loss(outputs, batch)

    @jax.jit
    def step(params, opt_state):
        (_, terms), grads = jax.value_and_grad(loss_fn, has_aux=True)(params)
        updates, opt_state = optimizer.update(grads, opt_state)
        return optax.apply_updates(params, updates), opt_state, terms

    params = variables["params"]
    losses = []
    for _ in range(40):
        params, opt_state, terms = step(params, opt_state)
        losses.append(float(terms["loss"]))
    assert np.all(np.isfinite(losses))
    assert losses[-1] < 0.3 * losses[0], losses

    outputs = apply_model({"params": params}, batch["image1"], batch["image2"], batch["flow"])
    pixels2, _ = photometric.reproject(
        1.0 / outputs["inv_depth_scales"][0],
        outputs["rotation"],
        outputs["translation"],
        batch["intrinsics1"],
    )
    # Pixels that stay in view (the last `shift` columns leave it), away from the border.
    flow = (np.asarray(pixels2) - geometry.pixel_grid(HEIGHT, WIDTH))[:, 2:-2, 2 : -shift - 2]
    np.testing.assert_allclose(np.median(flow, axis=(1, 2)), [[shift, 0.0]] * 2, atol=0.2)
    assert np.percentile(np.abs(flow[..., 0] - shift), 90) < 0.4
