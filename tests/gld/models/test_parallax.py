"""What the flow says under g's pose (`gld.models.parallax`): the triangulated flow as the
local network's channels (`GlobalLocal.parallax_depth`)."""

import global_local_reference as reference
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from gld import geometry
from gld.models import global_local as model_lib
from gld.models import parallax, registry

HEIGHT, WIDTH = 24, 32
INTRINSICS = np.array([[0.9, 1.2, 0.52, 0.47], [1.1, 1.4, 0.5, 0.5]], np.float32)


def _scene(translation, rotation_vector=(0.02, -0.04, 0.01), seed=0):
    rng = np.random.default_rng(seed)
    camera1, camera2 = (geometry.intrinsics_matrix(k, HEIGHT, WIDTH) for k in INTRINSICS)
    depth = rng.uniform(1.0, 5.0, (HEIGHT, WIDTH))
    rotation = geometry.rotation_matrix(np.array(rotation_vector, np.float64))
    translation = np.asarray(translation, np.float64)
    flow, valid = geometry.depth_to_flow(depth, camera1, camera2, rotation, translation)
    assert valid.all()
    return depth, flow, camera1, camera2, rotation, translation


def test_the_channel_is_the_inverse_depth_under_gs_pose_whatever_its_translations_norm():
    depth, flow, camera1, camera2, rotation, translation = _scene([0.6, -0.2, 0.1])
    unit = translation / np.linalg.norm(translation)
    intrinsics = [jnp.asarray(INTRINSICS[i : i + 1]) for i in (0, 1)]
    flows = jnp.asarray(flow, jnp.float32)[None]
    channels = [
        parallax.parallax_inverse_depth(
            flows,
            model_lib.pose_parameters(jnp.asarray(rotation)[None], jnp.asarray(t)[None]),
            *intrinsics,
        )
        for t in (unit, 3 * unit)
    ]
    assert channels[0].shape == (1, HEIGHT, WIDTH, 2)
    np.testing.assert_allclose(channels[0], channels[1], atol=1e-5)
    # In units of 1 / ||t||. The epipole is far outside the image: the ridge barely moves
    # it (and g's rotation is first order in the angle), and the confidence is near 1.
    expected = parallax.INVERSE_DEPTH_SCALE * np.linalg.norm(translation) / depth
    np.testing.assert_allclose(channels[0][0, ..., 0], expected, rtol=0.05)
    assert np.all(channels[0][..., 1] > 0.9) and np.all(channels[0][..., 1] < 1)
    # g enters as a constant: no gradient reaches it through the channel.
    params = model_lib.pose_parameters(jnp.asarray(rotation)[None], jnp.asarray(unit)[None])
    gradient = jax.grad(
        lambda g: parallax.parallax_inverse_depth(flows, g, *intrinsics)[..., 0].sum()
    )(params.astype(jnp.float32))
    assert np.all(np.asarray(gradient) == 0)


def test_near_the_epipole_the_channel_says_far_with_no_confidence_and_never_behind():
    # Forward motion: the epipole is inside the image.
    depth, flow, *_ = _scene([0.0, 0.0, 0.3], (0, 0, 0))
    intrinsics = [jnp.asarray(INTRINSICS[i : i + 1]) for i in (0, 1)]
    params = model_lib.pose_parameters(jnp.eye(3)[None], jnp.asarray([[0.0, 0.0, 1.0]]))
    inverse_depth, confidence = np.moveaxis(
        np.asarray(
            parallax.parallax_inverse_depth(jnp.asarray(flow)[None], params, *intrinsics)[0]
        ),
        -1,
        0,
    )
    centre = np.unravel_index(np.argmin(confidence), confidence.shape)
    assert confidence[centre] < 0.2 and confidence.max() > 0.9
    assert inverse_depth[centre] < 0.5 * parallax.INVERSE_DEPTH_SCALE * 0.3 / depth[centre]
    # A pose whose translation is the flow's reversed puts every point behind the
    # camera: clipped to 0, never negative.
    _, sideways, *_ = _scene([0.3, 0.0, 0.0], (0, 0, 0))
    backwards = model_lib.pose_parameters(jnp.eye(3)[None], jnp.asarray([[-1.0, 0.0, 0.0]]))
    behind = parallax.parallax_inverse_depth(jnp.asarray(sideways)[None], backwards, *intrinsics)
    forwards = parallax.parallax_inverse_depth(jnp.asarray(sideways)[None], -backwards, *intrinsics)
    assert np.all(np.asarray(behind)[..., 0] == 0.0)
    assert np.all(np.asarray(forwards)[..., 0] > 0.5)


@pytest.mark.parametrize("refinement_steps", [0, 2])
def test_the_local_network_sees_the_parallax_its_triangulation_and_the_coordinates(
    refinement_steps,
):
    model = model_lib.GlobalLocal(
        derotate_flow=True, parallax_depth=True, pose_refinement_steps=refinement_steps
    )
    assert model.extra_inputs == model_lib.CAMERA_INPUTS
    assert model.local_in_channels == 6
    rng = np.random.default_rng(0)
    inputs = (
        jnp.asarray(rng.uniform(-0.5, 0.5, (2, HEIGHT, WIDTH, 3)), jnp.float32),
        jnp.asarray(rng.uniform(-0.5, 0.5, (2, HEIGHT, WIDTH, 3)), jnp.float32),
        jnp.asarray(rng.normal(size=(2, HEIGHT, WIDTH, 2)) * 3, jnp.float32),
    )
    cameras = {"intrinsics1": jnp.asarray(INTRINSICS), "intrinsics2": jnp.asarray(INTRINSICS)}
    key = jax.random.key(0, impl="rbg")
    variables = jax.jit(lambda i, c: model.init(key, *i, **c))(inputs, cameras)
    variables = jax.tree.map(
        lambda x: x + 0.05 * rng.standard_normal(x.shape, np.float32), variables
    )
    outputs = jax.jit(model.apply)(variables, *inputs, **cameras)
    global_params = outputs["global_params"]
    flow_part = parallax.parallax_flow(inputs[2], global_params, *cameras.values())
    scaled = np.asarray(flow_part, np.float64) / [WIDTH, HEIGHT] * model.flow_scale
    channel = parallax.parallax_inverse_depth(inputs[2], global_params, *cameras.values())
    assert np.abs(channel).max() > 0.1
    grid = np.broadcast_to(reference.coordinates(HEIGHT, WIDTH), (2, HEIGHT, WIDTH, 2))
    banks = [(bank.kernel, bank.bias) for bank in outputs["filter_banks"]]
    local_inputs = np.concatenate([scaled, np.asarray(channel, np.float64), grid], axis=-1)
    logits = reference.local_network(banks, variables["params"]["final_conv"], local_inputs)
    np.testing.assert_allclose(outputs["inv_depth"], reference.inv_depth_of(logits), rtol=1e-4)
    with pytest.raises(ValueError, match="parallax_depth triangulates .* needs the cameras"):
        model_lib.GlobalLocal(parallax_depth=True).apply(variables, *inputs)
    # The depth loss's gradient is finite.

    def loss(params, model):
        outputs = model.apply({**variables, "params": params}, *inputs, **cameras)
        return jnp.mean(outputs["inv_depth"])

    gradient = jax.jit(jax.grad(loss), static_argnums=1)(variables["params"], model)
    assert all(bool(jnp.isfinite(leaf).all()) for leaf in jax.tree.leaves(gradient))


@pytest.mark.parametrize(
    "config",
    [
        {"global_source": "pose"},
        {"use_global_module": False},
        {"global_dim": 8},
        {"use_flow": False},
    ],
)
def test_the_triangulation_needs_a_pose_from_the_encoder_and_the_flow(config):
    with pytest.raises(ValueError, match="parallax_depth"):
        registry.check_config("global_local", {"parallax_depth": True, **config})
    registry.check_config("global_local", config)
