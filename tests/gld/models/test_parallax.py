"""What the flow says under g's pose (`gld.models.parallax`): the parallax alone
(`GlobalLocal.derotate_flow`) and the flow triangulated (`GlobalLocal.parallax_depth`) as
the local network's input."""

import global_local_reference as reference
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from two_view_scene import HEIGHT, INTRINSICS, WIDTH, two_view_scene

from gld import geometry
from gld.models import global_local as model_lib
from gld.models import parallax, registry


def _pose(rotation_vector, translation):
    return (
        geometry.rotation_matrix(np.asarray(rotation_vector, np.float32)),
        np.asarray(translation, np.float32),
    )


@pytest.mark.parametrize("xp", [np, jnp])
def test_a_rotations_flow_is_the_flow_of_points_at_infinity(xp):
    camera1, camera2 = (geometry.intrinsics_matrix(k, HEIGHT, WIDTH) for k in INTRINSICS)
    rotation, _ = _pose([0.03, -0.05, 0.02], [0, 0, 0])
    far = np.full((HEIGHT, WIDTH), 1e7, np.float32)
    expected, _ = geometry.depth_to_flow(far, camera1, camera2, rotation, np.zeros(3, np.float32))
    flow = geometry.rotation_flow(
        xp.asarray(rotation), xp.asarray(camera1), xp.asarray(camera2), HEIGHT, WIDTH
    )
    assert flow.shape == (HEIGHT, WIDTH, 2)
    np.testing.assert_allclose(flow, expected, atol=1e-3)
    assert np.abs(expected).max() > 1.0  # the rotation moves the pixels


def test_the_parallax_points_away_from_the_epipole_and_vanishes_without_translation():
    rng = np.random.default_rng(0)
    camera = geometry.intrinsics_matrix(INTRINSICS[0], HEIGHT, WIDTH)
    depth = rng.uniform(1.0, 5.0, (HEIGHT, WIDTH)).astype(np.float32)
    rotation, translation = _pose([0.02, -0.04, 0.01], [0.3, -0.1, 0.2])
    params = model_lib.pose_parameters(jnp.asarray(rotation)[None], jnp.asarray(translation)[None])
    intrinsics = jnp.asarray(INTRINSICS[:1])

    def parallax_of(translation):
        flow, _ = geometry.depth_to_flow(depth, camera, camera, rotation, translation)
        return np.asarray(
            parallax.parallax_flow(jnp.asarray(flow)[None], params, intrinsics, intrinsics)[0]
        )

    moved = parallax_of(translation)
    # Where the rotation alone takes each pixel, and the epipole: the parallax lies on the
    # line through both.
    rotated = geometry.pixel_grid(HEIGHT, WIDTH) + geometry.rotation_flow(
        rotation, camera, camera, HEIGHT, WIDTH
    )
    epipole = camera @ translation
    away = rotated - epipole[:2] / epipole[2]
    sine = (away[..., 0] * moved[..., 1] - away[..., 1] * moved[..., 0]) / (
        np.linalg.norm(away, axis=-1) * np.linalg.norm(moved, axis=-1)
    )
    assert np.abs(moved).mean() > 0.5
    assert np.abs(sine).max() < 1e-3
    # A pure rotation leaves none (the pose's round trip through g is first order in
    # the angle: ~3e-4 of 2.6 degrees).
    assert np.abs(parallax_of(np.zeros(3, np.float32))).max() < 0.01


def _inputs(seed=0):
    rng = np.random.default_rng(seed)
    return (
        jnp.asarray(rng.uniform(-0.5, 0.5, (2, HEIGHT, WIDTH, 3)), jnp.float32),
        jnp.asarray(rng.uniform(-0.5, 0.5, (2, HEIGHT, WIDTH, 3)), jnp.float32),
        jnp.asarray(rng.normal(size=(2, HEIGHT, WIDTH, 2)) * 3, jnp.float32),
    )


CAMERAS = {"intrinsics1": jnp.asarray(INTRINSICS), "intrinsics2": jnp.asarray(INTRINSICS)}


def _perturbed_variables(model, inputs):
    """The model's initial variables moved off their initialisation, so that every part
    of the network shapes the output."""
    key = jax.random.key(0, impl="rbg")
    variables = jax.jit(lambda i, c: model.init(key, *i, **c))(inputs, CAMERAS)
    rng = np.random.default_rng(1)
    return jax.tree.map(lambda x: x + 0.05 * rng.standard_normal(x.shape, np.float32), variables)


def _reference_inv_depth(outputs, variables, local_channels):
    """The numpy reference's local network on `local_channels` and the coordinates, with
    the banks the model generated."""
    grid = np.broadcast_to(reference.coordinates(HEIGHT, WIDTH), (2, HEIGHT, WIDTH, 2))
    banks = [(bank.kernel, bank.bias) for bank in outputs["filter_banks"]]
    local_inputs = np.concatenate([*local_channels, grid], axis=-1)
    logits = reference.local_network(banks, variables["params"]["final_conv"], local_inputs)
    return reference.inv_depth_of(logits)


def _scaled(model, parallax_pixels):
    return np.asarray(parallax_pixels, np.float64) / [WIDTH, HEIGHT] * model.flow_scale


@pytest.mark.slow
@pytest.mark.parametrize("refinement_steps", [0, 2])
def test_a_derotating_model_reads_the_cameras_and_its_local_network_sees_the_parallax(
    refinement_steps,
):
    model = model_lib.GlobalLocal(derotate_flow=True, pose_refinement_steps=refinement_steps)
    assert model.extra_inputs == model_lib.CAMERA_INPUTS
    inputs = _inputs()
    variables = _perturbed_variables(model, inputs)
    outputs = jax.jit(model.apply)(variables, *inputs, **CAMERAS)
    flow_part = parallax.parallax_flow(inputs[2], outputs["global_params"], *CAMERAS.values())
    expected = _reference_inv_depth(outputs, variables, [_scaled(model, flow_part)])
    np.testing.assert_allclose(outputs["inv_depth"], expected, rtol=1e-4)
    # The plain model with the same variables reads the flow itself.
    plain = model_lib.GlobalLocal(pose_refinement_steps=refinement_steps)
    plain_outputs = jax.jit(plain.apply)(
        variables, *inputs, **(CAMERAS if refinement_steps else {})
    )
    assert np.abs(plain_outputs["inv_depth"] - outputs["inv_depth"]).max() > 1e-4
    with pytest.raises(ValueError, match="needs the cameras: call with intrinsics1="):
        model.apply(variables, *inputs)


def test_the_channel_is_the_inverse_depth_under_gs_pose_whatever_its_translations_norm():
    depth, flow, camera1, camera2, rotation, translation = two_view_scene([0.6, -0.2, 0.1])
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
    depth, flow, *_ = two_view_scene([0.0, 0.0, 0.3], (0, 0, 0))
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
    _, sideways, *_ = two_view_scene([0.3, 0.0, 0.0], (0, 0, 0))
    backwards = model_lib.pose_parameters(jnp.eye(3)[None], jnp.asarray([[-1.0, 0.0, 0.0]]))
    behind = parallax.parallax_inverse_depth(jnp.asarray(sideways)[None], backwards, *intrinsics)
    forwards = parallax.parallax_inverse_depth(jnp.asarray(sideways)[None], -backwards, *intrinsics)
    assert np.all(np.asarray(behind)[..., 0] == 0.0)
    assert np.all(np.asarray(forwards)[..., 0] > 0.5)


@pytest.mark.slow
@pytest.mark.parametrize("refinement_steps", [0, 2])
def test_the_local_network_sees_the_parallax_its_triangulation_and_the_coordinates(
    refinement_steps,
):
    model = model_lib.GlobalLocal(
        derotate_flow=True, parallax_depth=True, pose_refinement_steps=refinement_steps
    )
    assert model.extra_inputs == model_lib.CAMERA_INPUTS
    assert model.local_in_channels == 6
    inputs = _inputs()
    variables = _perturbed_variables(model, inputs)
    outputs = jax.jit(model.apply)(variables, *inputs, **CAMERAS)
    global_params = outputs["global_params"]
    flow_part = parallax.parallax_flow(inputs[2], global_params, *CAMERAS.values())
    channel = parallax.parallax_inverse_depth(inputs[2], global_params, *CAMERAS.values())
    assert np.abs(channel).max() > 0.1
    channels = [_scaled(model, flow_part), np.asarray(channel, np.float64)]
    expected = _reference_inv_depth(outputs, variables, channels)
    np.testing.assert_allclose(outputs["inv_depth"], expected, rtol=1e-4)
    with pytest.raises(ValueError, match="parallax_depth triangulates .* needs the cameras"):
        model_lib.GlobalLocal(parallax_depth=True).apply(variables, *inputs)
    # The depth loss's gradient is finite.

    def loss(params, model):
        outputs = model.apply({**variables, "params": params}, *inputs, **CAMERAS)
        return jnp.mean(outputs["inv_depth"])

    gradient = jax.jit(jax.grad(loss), static_argnums=1)(variables["params"], model)
    assert all(bool(jnp.isfinite(leaf).all()) for leaf in jax.tree.leaves(gradient))


def test_a_model_given_its_pose_derotates_and_triangulates_the_flow_under_that_pose():
    model = model_lib.GlobalLocal(global_source="pose", derotate_flow=True, parallax_depth=True)
    assert model.extra_inputs == (*model_lib.POSE_INPUTS, *model_lib.CAMERA_INPUTS)
    inputs = _inputs()
    poses = [
        _pose([0.01, -0.02, 0.005], [0.2, 0.1, 1.0]),
        _pose([0.0, 0.01, 0.0], [-1.0, 0.0, 0.3]),
    ]
    pose = {
        "rotation": jnp.asarray(np.stack([rotation for rotation, _ in poses])),
        "translation": jnp.asarray(np.stack([translation for _, translation in poses])),
    }
    key = jax.random.key(0, impl="rbg")
    variables = model.init(key, *inputs, **pose, **CAMERAS)
    outputs = jax.jit(model.apply)(variables, *inputs, **pose, **CAMERAS)
    given = model_lib.pose_parameters(pose["rotation"], pose["translation"])
    np.testing.assert_allclose(outputs["global_params"], given, atol=1e-6)
    flow_part = parallax.parallax_flow(inputs[2], given, *CAMERAS.values())
    channel = parallax.parallax_inverse_depth(inputs[2], given, *CAMERAS.values())
    channels = [_scaled(model, flow_part), np.asarray(channel, np.float64)]
    expected = _reference_inv_depth(outputs, variables, channels)
    np.testing.assert_allclose(outputs["inv_depth"], expected, rtol=1e-4)
    # Another pose given, another depth: the local network reads the pose given.
    turned = {**pose, "translation": pose["translation"][::-1]}
    other = jax.jit(model.apply)(variables, *inputs, **turned, **CAMERAS)
    assert np.abs(other["inv_depth"] - outputs["inv_depth"]).max() > 1e-4


@pytest.mark.parametrize(
    "config", [{"use_global_module": False}, {"global_dim": 8}, {"use_flow": False}]
)
def test_the_triangulation_needs_a_pose_as_g_and_the_flow(config):
    with pytest.raises(ValueError, match="parallax_depth"):
        registry.check_config("global_local", {"parallax_depth": True, **config})
    registry.check_config("global_local", config)


@pytest.mark.parametrize(
    "config", [{"use_global_module": False}, {"global_dim": 8}, {"use_flow": False}]
)
def test_derotation_needs_a_pose_as_g_and_the_flow(config):
    with pytest.raises(ValueError, match="derotate_flow"):
        registry.check_config("global_local", {"derotate_flow": True, **config})
    registry.check_config("global_local", config)
