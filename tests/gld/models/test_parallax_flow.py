"""The local network given the parallax alone (`GlobalLocal.derotate_flow`)."""

import global_local_reference as reference
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from gld import geometry
from gld.models import global_local as model_lib
from gld.models import registry

HEIGHT, WIDTH = 24, 32
INTRINSICS = np.array([[0.9, 1.2, 0.52, 0.47], [1.1, 1.4, 0.5, 0.5]], np.float32)


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

    def parallax(translation):
        flow, _ = geometry.depth_to_flow(depth, camera, camera, rotation, translation)
        return np.asarray(
            model_lib.parallax_flow(jnp.asarray(flow)[None], params, intrinsics, intrinsics)[0]
        )

    moved = parallax(translation)
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
    assert np.abs(parallax(np.zeros(3, np.float32))).max() < 0.01


def _inputs(seed=0):
    rng = np.random.default_rng(seed)
    return (
        jnp.asarray(rng.uniform(-0.5, 0.5, (2, HEIGHT, WIDTH, 3)), jnp.float32),
        jnp.asarray(rng.uniform(-0.5, 0.5, (2, HEIGHT, WIDTH, 3)), jnp.float32),
        jnp.asarray(rng.normal(size=(2, HEIGHT, WIDTH, 2)) * 3, jnp.float32),
    )


@pytest.mark.parametrize("refinement_steps", [0, 2])
def test_a_derotating_model_reads_the_cameras_and_its_local_network_sees_the_parallax(
    refinement_steps,
):
    model = model_lib.GlobalLocal(derotate_flow=True, pose_refinement_steps=refinement_steps)
    assert model.extra_inputs == model_lib.CAMERA_INPUTS
    inputs = _inputs()
    cameras = {"intrinsics1": jnp.asarray(INTRINSICS), "intrinsics2": jnp.asarray(INTRINSICS)}
    key = jax.random.key(0, impl="rbg")
    variables = jax.jit(lambda i, c: model.init(key, *i, **c))(inputs, cameras)
    rng = np.random.default_rng(1)
    variables = jax.tree.map(
        lambda x: x + 0.05 * rng.standard_normal(x.shape, np.float32), variables
    )
    outputs = jax.jit(model.apply)(variables, *inputs, **cameras)
    global_params = outputs["global_params"]
    parallax = model_lib.parallax_flow(inputs[2], global_params, *cameras.values())
    scaled = np.asarray(parallax, np.float64) / [WIDTH, HEIGHT] * model.flow_scale
    grid = np.broadcast_to(reference.coordinates(HEIGHT, WIDTH), (2, HEIGHT, WIDTH, 2))
    banks = [(bank.kernel, bank.bias) for bank in outputs["filter_banks"]]
    logits = reference.local_network(
        banks, variables["params"]["final_conv"], np.concatenate([scaled, grid], axis=-1)
    )
    np.testing.assert_allclose(outputs["inv_depth"], reference.inv_depth_of(logits), rtol=1e-4)
    # The plain model with the same variables reads the flow itself.
    plain = model_lib.GlobalLocal(pose_refinement_steps=refinement_steps)
    plain_outputs = jax.jit(plain.apply)(
        variables, *inputs, **(cameras if refinement_steps else {})
    )
    assert np.abs(plain_outputs["inv_depth"] - outputs["inv_depth"]).max() > 1e-4
    with pytest.raises(ValueError, match="needs the cameras: call with intrinsics1="):
        model.apply(variables, *inputs)


@pytest.mark.parametrize(
    "config", [{"global_source": "pose"}, {"use_global_module": False}, {"global_dim": 8}]
)
def test_derotation_needs_a_pose_from_the_encoder(config):
    with pytest.raises(ValueError, match="derotate_flow"):
        registry.check_config("global_local", {"derotate_flow": True, **config})
    registry.check_config("global_local", config)
