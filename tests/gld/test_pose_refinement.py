"""Refining a pose on the flow's epipolar geometry (`gld.pose_refinement`) and the model
whose global parameters are its encoder's pose refined so (`pose_refinement_steps`)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from gld import geometry, pose_refinement
from gld.losses import supervised as losses
from gld.models import global_local as model_lib
from gld.models import registry
from gld.runs import state

HEIGHT, WIDTH = 48, 64
INTRINSICS = np.array([[0.9, 1.2, 0.5, 0.5], [0.85, 1.1, 0.52, 0.47]], np.float32)


def _pairs():
    """Exact flow of two bumpy, slanted surfaces under known motions, and those motions."""
    grid = geometry.pixel_grid(HEIGHT, WIDTH).astype(np.float64)
    depths = [
        3.0 + 0.02 * grid[..., 0] + 0.5 * np.sin(grid[..., 1] / 5.0),
        2.0 + 1.5 * (grid[..., 1] / HEIGHT) + 0.3 * np.cos(grid[..., 0] / 7.0),
    ]
    rotations = geometry.rotation_matrix(np.array([[0.0, 0.03, 0.01], [0.02, -0.01, 0.005]]))
    translations = np.array([[0.3, 0.05, 0.1], [-0.1, 0.2, 0.3]])
    flows = []
    for depth, intrinsics, rotation, translation in zip(
        depths, INTRINSICS, rotations, translations, strict=True
    ):
        camera = geometry.intrinsics_matrix(intrinsics.astype(np.float64), HEIGHT, WIDTH)
        flows.append(geometry.depth_to_flow(depth, camera, camera, rotation, translation)[0])
    return np.stack(flows).astype(np.float32), rotations, translations


def _turned(rotations, translations, rotation_degrees, translation_degrees):
    """The poses off by the given angles (about fixed axes)."""
    axis = np.array([0.6, -0.8, 0.0])
    rotation = geometry.rotation_matrix(np.radians(rotation_degrees) * axis) @ rotations
    turn = [
        geometry.rotation_matrix(
            np.radians(translation_degrees)
            * np.cross(t, [0, 0, 1])
            / np.linalg.norm(np.cross(t, [0, 0, 1]))
        )
        for t in translations
    ]
    translation = np.stack([r @ t for r, t in zip(turn, translations, strict=True)])
    return rotation.astype(np.float32), translation.astype(np.float32)


def _errors(rotation, translation, rotations, translations):
    return (
        geometry.rotation_error_degrees(np.asarray(rotation, np.float64), rotations),
        geometry.translation_error_degrees(np.asarray(translation, np.float64), translations),
    )


def test_refinement_brings_a_proposal_off_by_degrees_to_the_true_motion():
    flow, rotations, translations = _pairs()
    proposal = _turned(rotations, translations, 2.0, 20.0)
    before = _errors(*proposal, rotations, translations)
    assert np.all(before[0] > 1.9) and np.all(before[1] > 15)
    rotation, translation = pose_refinement.refine_pose(
        jnp.asarray(flow),
        *map(jnp.asarray, proposal),
        jnp.asarray(INTRINSICS),
        jnp.asarray(INTRINSICS),
    )
    after = _errors(rotation, translation, rotations, translations)
    assert np.all(after[0] < 0.05) and np.all(after[1] < 0.5), after
    np.testing.assert_allclose(np.linalg.norm(translation, axis=-1), 1.0, atol=1e-5)
    # Zero steps return the proposal (the translation at unit norm).
    same = pose_refinement.refine_pose(
        jnp.asarray(flow),
        *map(jnp.asarray, proposal),
        jnp.asarray(INTRINSICS),
        jnp.asarray(INTRINSICS),
        iterations=0,
    )
    np.testing.assert_allclose(same[0], proposal[0], atol=1e-6)
    with pytest.raises(ValueError, match="stride >= 1"):
        pose_refinement.refine_pose(
            jnp.asarray(flow),
            *map(jnp.asarray, proposal),
            jnp.asarray(INTRINSICS),
            jnp.asarray(INTRINSICS),
            stride=0,
        )


def test_the_closed_form_jacobian_is_the_derivative_of_the_distances():
    flow, rotations, translations = _pairs()
    rotation, translation = _turned(rotations, translations, 2.0, 20.0)
    translation = translation[0] / np.linalg.norm(translation[0])
    inverse_k = np.linalg.inv(geometry.intrinsics_matrix(INTRINSICS[0], HEIGHT, WIDTH))
    x1, x2, _ = pose_refinement._rays(jnp.asarray(flow[0]), inverse_k, inverse_k, 4)
    basis = pose_refinement._tangent_basis(jnp.asarray(translation))
    focal = INTRINSICS[0, 0] * WIDTH

    def distances(step):
        moved = pose_refinement._moved(jnp.asarray(rotation[0]), translation, step, basis)
        return pose_refinement._distances_and_jacobian(x1, x2, *moved, basis, focal)[0]

    distance, jacobian = pose_refinement._distances_and_jacobian(
        x1, x2, jnp.asarray(rotation[0]), jnp.asarray(translation), basis, focal
    )
    automatic = jax.jacfwd(distances)(jnp.zeros(5, jnp.float32))
    assert np.abs(distance).max() > 0.5  # off the motion: the distances are not zero
    signed = pose_refinement._signed_distances(x1, x2, rotation[0], translation, focal)
    np.testing.assert_allclose(distance, signed, rtol=1e-4, atol=1e-4)
    np.testing.assert_allclose(
        jacobian.T, automatic, rtol=1e-3, atol=1e-3 * np.abs(automatic).max()
    )


@pytest.mark.slow
def test_a_search_around_the_proposal_finds_the_motion_where_one_start_stops_in_a_wrong_basin():
    flow, rotations, translations = _pairs()
    cameras = (jnp.asarray(INTRINSICS), jnp.asarray(INTRINSICS))
    proposal = tuple(map(jnp.asarray, _turned(rotations, translations, 3.0, 60.0)))
    single = pose_refinement.pose_from_proposal(
        jnp.asarray(flow), *proposal, *cameras, iterations=15
    )
    searched = pose_refinement.pose_from_proposal(
        jnp.asarray(flow), *proposal, *cameras, iterations=15, starts=5
    )
    # One start, fifteen steps: the refinement stays ~5-10 deg / 70 deg off on both pairs.
    single_errors = _errors(*single, rotations, translations)
    assert np.all(single_errors[0] > 2) and np.all(single_errors[1] > 30), single_errors
    searched_errors = _errors(*searched, rotations, translations)
    assert np.all(searched_errors[0] < 0.1) and np.all(searched_errors[1] < 0.1), searched_errors
    np.testing.assert_allclose(np.linalg.norm(searched[1], axis=-1), 1.0, atol=1e-5)
    # What the search picks by: the robust cost is lower at the motion than where one
    # start stopped, and ~0 on exact flow.
    cost = {
        name: np.asarray(pose_refinement.robust_cost(jnp.asarray(flow), *pose, *cameras))
        for name, pose in (("single", single), ("searched", searched))
    }
    assert np.all(cost["searched"] < 1e-4) and np.all(cost["single"] > 1.0), cost
    # One start is `refine_pose` itself.
    np.testing.assert_array_equal(
        single[1],
        pose_refinement.refine_pose(jnp.asarray(flow), *proposal, *cameras, iterations=15)[1],
    )
    # No steps: the proposal, with no search.
    unmoved = pose_refinement.pose_from_proposal(
        jnp.asarray(flow), *proposal, *cameras, iterations=0, starts=5
    )
    np.testing.assert_allclose(unmoved[0], proposal[0], atol=1e-6)
    # The model's g is the searched pose.
    model = model_lib.GlobalLocal(
        encoder_channels=(4, 8, 8, 8, 8), pose_refinement_steps=15, pose_refinement_starts=5
    )
    variables = state.init_variables(model, HEIGHT, WIDTH, seed=0)
    params = jax.tree_util.tree_map(lambda x: x, variables["params"])
    to_global = params["global_encoder"]["to_global"]
    to_global["kernel"] = jnp.zeros_like(to_global["kernel"])
    to_global["bias"] = model_lib.pose_parameters(*proposal)[0]
    images = jnp.zeros((2, HEIGHT, WIDTH, 3))
    outputs = model.apply(
        {"params": params},
        images,
        images,
        jnp.asarray(flow),
        **dict(zip(("intrinsics1", "intrinsics2"), cameras, strict=True)),
    )
    pose = outputs["global_pose"]
    model_errors = _errors(
        pose["rotation"][0], pose["translation"][0], rotations[0], translations[0]
    )
    assert model_errors[0] < 0.1 and model_errors[1] < 0.1, model_errors
    with pytest.raises(ValueError, match="starts must be >= 1"):
        pose_refinement.search_pose(jnp.asarray(flow), *proposal, *cameras, starts=0)
    with pytest.raises(ValueError, match="needs pose_refinement_steps"):
        registry.check_config("global_local", {"pose_refinement_starts": 5})
    with pytest.raises(ValueError, match="pose_refinement_starts"):
        registry.check_config(
            "global_local", {"pose_refinement_starts": 0, "pose_refinement_steps": 5}
        )


@pytest.mark.slow
def test_a_model_refining_its_encoder_pose_gives_the_refined_pose_as_g_and_trains_the_proposal():
    flow, rotations, translations = _pairs()
    model = model_lib.GlobalLocal(encoder_channels=(4, 8, 8, 8, 8), pose_refinement_steps=10)
    assert model.extra_inputs == ("intrinsics1", "intrinsics2")
    variables = state.init_variables(model, HEIGHT, WIDTH, seed=0)
    # Point the proposal at the true motion off by 2 / 20 degrees: the encoder's last conv
    # gives it through its bias (its kernel zeroed).
    proposal = model_lib.pose_parameters(
        *map(jnp.asarray, _turned(rotations, translations, 2.0, 20.0))
    )
    params = jax.tree_util.tree_map(lambda x: x, variables["params"])
    to_global = params["global_encoder"]["to_global"]
    to_global["kernel"] = jnp.zeros_like(to_global["kernel"])
    images = jnp.zeros((2, HEIGHT, WIDTH, 3))
    cameras = dict(intrinsics1=jnp.asarray(INTRINSICS), intrinsics2=jnp.asarray(INTRINSICS))
    errors = []
    for index in range(2):
        to_global["bias"] = proposal[index]
        outputs = model.apply({"params": params}, images, images, jnp.asarray(flow), **cameras)
        np.testing.assert_allclose(outputs["encoder_params"][index], proposal[index], atol=1e-5)
        pose = outputs["global_pose"]
        errors.append(
            _errors(
                pose["rotation"][index],
                pose["translation"][index],
                rotations[index],
                translations[index],
            )
        )
    assert all(r < 0.1 and t < 1.0 for r, t in errors), errors
    with pytest.raises(ValueError, match="intrinsics1= and intrinsics2="):
        model.apply({"params": params}, images, images, jnp.asarray(flow))
    with pytest.raises(ValueError, match="must not read"):
        registry.check_config("global_local", {"pose_refinement_steps": 5, "use_flow": False})
    with pytest.raises(ValueError, match="global_source encoder and global_dim 6"):
        registry.check_config("global_local", {"pose_refinement_steps": 5, "global_source": "pose"})
    # The losses on g's pose train the encoder's proposal, not the refined pose: the
    # teacher is at the true pose, so the refined g would score ~0, the proposal does not.
    batch = {
        "flow_rotation": jnp.asarray(rotations, jnp.float32),
        "flow_translation": jnp.asarray(
            translations / np.linalg.norm(translations, axis=-1, keepdims=True), jnp.float32
        ),
    }
    to_global["bias"] = proposal[0]
    outputs = model.apply({"params": params}, images, images, jnp.asarray(flow), **cameras)
    assert float(losses.pose_teacher_term(outputs, batch)) > 0.05
    gradient = jax.grad(
        lambda p: losses.pose_teacher_term(
            model.apply({"params": p}, images, images, jnp.asarray(flow), **cameras), batch
        )
    )(params)
    assert float(jnp.abs(gradient["global_encoder"]["to_global"]["bias"]).max()) > 0


@pytest.mark.slow  # 300 training steps: ~40 s on the 2-core CPU
def test_the_pose_teacher_teaches_the_encoder_the_motion_and_refinement_sharpens_it(
    tiny_scenes, tmp_path
):
    from conftest import TINY_MODEL, tiny_train_config

    from gld.analysis import probes
    from gld.models import layers
    from gld.runs import workdir as workdir_lib
    from gld.training import trainer as train

    source = tiny_scenes.as_data_source("train")
    model_config = {
        **TINY_MODEL,
        "use_image_pair": False,
        "encoder_norm": "instance",
        "pose_refinement_steps": 10,
    }

    def pose_errors(steps):
        workdir = tmp_path / f"steps_{steps}"
        config = tiny_train_config(
            steps=steps,
            checkpoint_every=steps,
            log_every=steps,
            flow_source="gt",
            pose_teacher_weight=1.0,
            learning_rate=1e-3 if steps > 1 else 1e-12,
            lr_schedule="cosine",
            warmup_steps=min(20, steps - 1),
            model_config=model_config,
        )
        train.train_and_evaluate(config, workdir, source, progress=False, print_fn=lambda _: None)
        model, variables, _ = workdir_lib.load_trained(workdir)
        apply = jax.jit(lambda batch: layers.apply_model(model, variables, batch))

        def read_as_g(output):
            def outputs(batch):
                result = apply({key: batch[key] for key in layers.input_keys(model)})
                return {"inv_depth": result["inv_depth"], "global_params": result[output]}

            return outputs

        errors = {}
        for output in ("encoder_params", "global_params"):
            collected = probes.collect(read_as_g(output), source, flow_source="gt")
            errors[output] = probes.global_params_pose_errors(collected)
        return errors

    untrained, trained = pose_errors(1), pose_errors(300)
    # Measured: the proposal 3.8 / 61 deg untrained, 2.7 / 42 deg after 300 steps; the
    # refined g 2.7 / 30 deg and 1.2 / 14 deg.
    assert untrained["encoder_params"]["rotation_deg"] > 3.3
    assert trained["encoder_params"]["rotation_deg"] < 3.2
    assert trained["encoder_params"]["translation_deg"] < 52
    assert trained["global_params"]["rotation_deg"] < 1.8
    assert trained["global_params"]["translation_deg"] < 22
    for output in ("rotation_deg", "translation_deg"):
        assert trained["global_params"][output] < trained["encoder_params"][output]
