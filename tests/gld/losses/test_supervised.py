import jax
import jax.numpy as jnp
import numpy as np
import pytest

from gld.losses import supervised as losses


def _batch(depth, mask, image=None):
    height, width = depth.shape[-2:]
    image = np.zeros((1, height, width, 3), np.float32) if image is None else image
    return {"depth": depth[None], "sparse_mask": mask[None], "image1": image}


def test_loss_is_zero_when_the_prediction_is_the_ground_truth_and_constant():
    depth = np.full((4, 5), 2.0, np.float32)
    mask = np.zeros((4, 5), bool)
    mask[1, 2] = True
    outputs = {"inv_depth": jnp.full((1, 4, 5), 0.5)}
    loss, terms = losses.total_loss(outputs, _batch(depth, mask))
    assert float(loss) == pytest.approx(0.0)
    assert float(terms["smoothness"]) == pytest.approx(0.0)


def test_sparse_l1_by_hand():
    prediction = jnp.array([[[0.5, 0.1], [0.2, 0.3]]])
    target = jnp.array([[[0.25, 9.0], [0.4, 9.0]]])
    mask = jnp.array([[[True, False], [True, False]]])
    # (|0.5 - 0.25| + |0.2 - 0.4|) / 2 supervised pixels
    assert float(losses.sparse_l1(prediction, target, mask)) == pytest.approx(0.225)
    assert float(losses.sparse_l1(prediction, target, jnp.zeros_like(mask))) == 0.0


def test_edge_aware_smoothness_by_hand():
    inv_depth = jnp.array([[[0.0, 1.0], [0.0, 1.0]]])
    flat = jnp.zeros((1, 2, 2, 3))
    # both rows step by 1 in x (mean over the [1, 2, 1] difference map), no change in y
    assert float(losses.edge_aware_smoothness(inv_depth, flat)) == pytest.approx(1.0)
    edge = flat.at[:, :, 1, :].set(1.0)  # an image edge where depth jumps: penalty * e^-1
    assert float(losses.edge_aware_smoothness(inv_depth, edge)) == pytest.approx(np.exp(-1))
    vertical = jnp.swapaxes(inv_depth, 1, 2)
    assert float(losses.edge_aware_smoothness(vertical, flat)) == pytest.approx(1.0)


def test_weights_and_target_inversion():
    depth = np.full((2, 2), 4.0, np.float32)
    mask = np.array([[True, False], [False, False]])
    outputs = {"inv_depth": jnp.full((1, 2, 2), 0.5)}
    weights = losses.LossWeights(depth=3.0, smoothness=0.0)
    loss, terms = losses.total_loss(outputs, _batch(depth, mask), weights)
    assert float(terms["depth_l1"]) == pytest.approx(0.25)
    assert float(loss) == pytest.approx(0.75)


def test_pyramid_levels_add_their_own_error():
    depth = np.full((4, 4), 2.0, np.float32)
    mask = np.ones((4, 4), bool)
    exact = {"inv_depth": jnp.full((1, 4, 4), 0.5)}
    with_coarse = dict(exact, inv_depth_pyramid=(jnp.full((1, 2, 2), 0.7),))
    _, terms = losses.total_loss(with_coarse, _batch(depth, mask))
    assert float(terms["depth_l1"]) == pytest.approx(0.1)  # (0 + 0.2) / 2 scales
    _, terms = losses.total_loss(exact, _batch(depth, mask))
    assert float(terms["depth_l1"]) == pytest.approx(0.0)


def test_epipolar_term_is_the_mean_epipolar_distance_of_the_pose_g_stands_for():
    from gld import geometry
    from gld.models import global_local as model_lib

    rng = np.random.default_rng(0)
    flow = jnp.asarray(rng.normal(size=(2, 12, 16, 2)), jnp.float32)
    global_params = jnp.asarray(rng.normal(size=(2, 6)) * 0.5, jnp.float32)
    pose = model_lib.global_params_pose(global_params)
    intrinsics = jnp.asarray([[0.9, 1.2, 0.5, 0.5]] * 2, jnp.float32)
    batch = {"flow": flow, "intrinsics1": intrinsics, "intrinsics2": intrinsics}
    expected = np.mean(
        geometry.epipolar_distance(
            flow, pose["rotation"], pose["translation"], intrinsics, intrinsics
        )
    )
    np.testing.assert_allclose(losses.epipolar_term({"global_pose": pose}, batch), expected)
    with pytest.raises(ValueError, match="six global parameters stand for a pose"):
        losses.epipolar_term({"inv_depth": flow[..., 0]}, batch)
    # total_loss adds the term only when it is weighted.
    inv_depth = jnp.full((2, 12, 16), 0.2, jnp.float32)
    batch.update(
        depth=jnp.full((2, 12, 16), 4.0, jnp.float32),
        sparse_mask=jnp.ones((2, 12, 16), bool),
        image1=jnp.zeros((2, 12, 16, 3), jnp.float32),
    )
    outputs = {"inv_depth": inv_depth, "global_pose": pose}
    plain, plain_terms = losses.total_loss(outputs, batch)
    weighted, terms = losses.total_loss(outputs, batch, losses.LossWeights(epipolar=0.5))
    assert "epipolar" not in plain_terms
    np.testing.assert_allclose(terms["epipolar"], expected, rtol=1e-6)
    np.testing.assert_allclose(weighted, plain + 0.5 * expected, rtol=1e-6)


def test_pose_teacher_term_is_the_distance_of_g_from_the_flow_pose_over_pairs_it_holds_for():
    from gld import geometry
    from gld.models import global_local as model_lib

    rotation = jnp.asarray(geometry.rotation_matrix(np.array([[0.0, 0.05, 0.0]] * 3)), jnp.float32)
    translation = jnp.asarray([[1.0, 0.0, 0.0], [0.0, 0.6, 0.8], [0.0, 0.0, 0.0]], jnp.float32)
    target = model_lib.pose_parameters(rotation, translation)
    global_params = target + jnp.asarray([[0.1, 0, 0, 0, 0, 0], [0, 0, 0, 0.2, 0, 0], [5.0] * 6])
    batch = {"flow_rotation": rotation, "flow_translation": translation}
    outputs = {"global_params": global_params, "global_pose": {}}
    # The third pair's estimate failed (zero translation): it does not count.
    np.testing.assert_allclose(
        losses.pose_teacher_term(outputs, batch), (0.1**2 + 0.2**2) / 2, rtol=1e-5
    )
    exact = {"global_params": target[:2], "global_pose": {}}
    two = {key: value[:2] for key, value in batch.items()}
    np.testing.assert_allclose(losses.pose_teacher_term(exact, two), 0.0, atol=1e-10)
    # The teacher is a target: no gradient flows into it.
    gradient = jax.grad(
        lambda r: losses.pose_teacher_term(
            outputs, {"flow_rotation": r, "flow_translation": translation}
        )
    )(rotation)
    np.testing.assert_array_equal(gradient, 0.0)
    with pytest.raises(ValueError, match="six global parameters stand for a pose"):
        losses.pose_teacher_term({"global_params": global_params}, batch)
