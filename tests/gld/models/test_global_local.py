import global_local_reference as reference
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from gld.losses import supervised as losses
from gld.models import filter_banks as filter_banks_lib
from gld.models import global_local as model_lib
from gld.models import hypernet, layers, registry


def _inputs(batch=2, height=24, width=32, seed=0):
    rng = np.random.default_rng(seed)
    return (
        jnp.asarray(rng.uniform(-0.5, 0.5, (batch, height, width, 3)), jnp.float32),
        jnp.asarray(rng.uniform(-0.5, 0.5, (batch, height, width, 3)), jnp.float32),
        jnp.asarray(rng.normal(size=(batch, height, width, 2)) * 3, jnp.float32),
    )


def _init(model, *inputs, **extra):
    # Compiled, with the 'rbg' generator: op by op, the paper model's init takes seconds.
    key = jax.random.key(0, impl="rbg")
    return jax.jit(lambda inputs, extra: model.init(key, *inputs, **extra))(inputs, extra)


@pytest.fixture(scope="module")
def paper_model():
    """The paper's model, its initial variables, a batch of two 32x24 pairs, and its
    compiled apply."""
    model = model_lib.GlobalLocal()
    inputs = _inputs()
    return model, _init(model, *inputs), inputs, jax.jit(model.apply)


def test_paper_architecture_shapes_and_hypernetwork_size(paper_model):
    model, variables, (image1, image2, flow), apply = paper_model
    outputs = apply(variables, image1, image2, flow)
    assert outputs["inv_depth"].shape == (2, 24, 32)
    assert bool(jnp.all(outputs["inv_depth"] > 0))
    np.testing.assert_allclose(outputs["depth"] * outputs["inv_depth"], 1.0, rtol=1e-5)
    assert outputs["global_params"].shape == (2, 6)
    shapes = [(b.kernel.shape, b.bias.shape) for b in outputs["filter_banks"]]
    assert shapes == [
        ((2, 3, 3, 4, 20), (2, 20)),
        ((2, 3, 3, 20, 10), (2, 10)),
        ((2, 3, 3, 10, 20), (2, 20)),
    ]
    assert hypernet.hypernet_output_size() == 4370
    counts = registry.parameter_counts(variables["params"])
    assert counts["hypernet"] == 6 * 4370 + 4370
    assert counts["final_conv"] == 3 * 3 * 20 + 1


def test_the_model_is_the_documented_network_written_out_in_numpy(paper_model):
    # Every parameter moved off its initial value (zero biases would hide a misplaced one).
    model, variables, inputs, apply = paper_model
    rng = np.random.default_rng(1)
    variables = jax.tree.map(
        lambda x: x + 0.05 * rng.standard_normal(x.shape, np.float32), variables
    )
    outputs = apply(variables, *inputs)
    expected = reference.global_local(model, variables, *(np.asarray(x) for x in inputs))
    np.testing.assert_allclose(
        outputs["global_params"], expected["global_params"], rtol=1e-4, atol=1e-6
    )
    # Each pair's filters are the hypernetwork's linear map of its own global parameters.
    for bank, (kernel, bias) in zip(outputs["filter_banks"], expected["banks"], strict=True):
        np.testing.assert_allclose(bank.kernel, kernel, rtol=1e-4, atol=1e-5)
        np.testing.assert_allclose(bank.bias, bias, rtol=1e-4, atol=1e-5)
    np.testing.assert_allclose(outputs["inv_depth"], expected["inv_depth"], rtol=1e-4)
    np.testing.assert_allclose(outputs["depth"], expected["depth"], rtol=1e-4)


@pytest.mark.parametrize(
    "ablation, local_channels",
    [
        ({"use_image_pair": False}, 4),
        ({"use_coordinates": False}, 2),
        ({"use_global_module": False}, 4),
        ({"use_flow": False}, 8),
    ],
)
def test_ablations_change_what_the_model_sees(ablation, local_channels):
    model = model_lib.GlobalLocal(**ablation)
    image1, image2, flow = _inputs()
    # Shapes alone, unless the check reads values (computing them compiles the model).
    needs_values = ablation.get("use_global_module") is False or ablation.get("use_flow") is False
    if needs_values:
        variables = _init(model, image1, image2, flow)
        apply = jax.jit(model.apply)
        outputs = apply(variables, image1, image2, flow)
    else:
        outputs, variables = jax.eval_shape(
            model.init_with_output, jax.random.key(0), image1, image2, flow
        )
    assert outputs["filter_banks"][0].kernel.shape[-2] == local_channels
    assert outputs["inv_depth"].shape == (2, 24, 32)
    params = variables["params"]
    if ablation.get("use_global_module") is False:
        assert "global_encoder" not in params and "static_filters" in params
        # static filters: every example gets the same bank
        np.testing.assert_array_equal(
            outputs["filter_banks"][0].kernel[0], outputs["filter_banks"][0].kernel[1]
        )
    if ablation.get("use_image_pair") is False:
        assert params["global_encoder"]["conv0"]["kernel"].shape[-2] == 2
    if ablation.get("use_flow") is False:
        # flow must not matter at all
        other = apply(variables, image1, image2, flow * 0 + 5.0)
        np.testing.assert_allclose(other["inv_depth"], outputs["inv_depth"], rtol=1e-6)


def test_gradients_reach_the_hypernetwork_and_the_global_encoder(paper_model):
    model, variables, (image1, image2, flow), _ = paper_model
    batch = {
        "image1": image1,
        "depth": jnp.full((2, 24, 32), 3.0),
        "sparse_mask": jnp.zeros((2, 24, 32), bool).at[:, 5, 7].set(True),
    }

    def loss_fn(params):
        outputs = model.apply({"params": params}, image1, image2, flow)
        return losses.total_loss(outputs, batch)[0]

    grads = jax.jit(jax.grad(loss_fn))(variables["params"])
    for module in ("global_encoder", "hypernet", "final_conv"):
        norm = sum(float(jnp.sum(g**2)) for g in jax.tree_util.tree_leaves(grads[module]))
        assert norm > 0, module
    first_conv = grads["global_encoder"]["conv0"]["kernel"]
    assert float(jnp.abs(first_conv).sum()) > 0


def test_bad_inputs_are_named(paper_model):
    model, variables, (image1, image2, flow), _ = paper_model
    with pytest.raises(ValueError, match="flow"):
        model.apply(variables, image1, image2, flow[..., :1])
    with pytest.raises(ValueError, match="image2"):
        model.apply(variables, image1, image2[:, :10], flow)
    with pytest.raises(ValueError, match="unknown model"):
        registry.make_model("resnet9000")


def _local_network_by_hand(variables, filter_banks, local_flow):
    """The local network on [local_flow, x, y] with the given banks and the final conv."""
    batch, height, width, _ = local_flow.shape
    y, x = jnp.meshgrid(
        jnp.linspace(-1.0, 1.0, height), jnp.linspace(-1.0, 1.0, width), indexing="ij"
    )
    coordinates = jnp.broadcast_to(jnp.stack([x, y], -1), (batch, height, width, 2))
    final_conv = variables["params"]["final_conv"]
    logits = filter_banks_lib.apply_filter_banks(
        filter_banks,
        jnp.concatenate([local_flow, coordinates], -1),
        head=filter_banks_lib.SharedConv(final_conv["kernel"], final_conv["bias"]),
        formulation="vmap",
    )
    return layers.depth_outputs(logits)["inv_depth"]


def test_local_flow_units_scale_only_the_local_input(paper_model):
    normalised, variables, (image1, image2, flow), apply = paper_model
    pixels = model_lib.GlobalLocal(local_flow_units="pixels")
    # Same parameters: the global module sees flow / [W, H] * flow_scale in both models,
    # so both generate the same filters; the local network sees that same normalised
    # flow in one and the flow in pixels in the other.
    a = jax.jit(pixels.apply)(variables, image1, image2, flow)
    b = apply(variables, image1, image2, flow)
    np.testing.assert_allclose(a["global_params"], b["global_params"], rtol=1e-6)
    for bank_a, bank_b in zip(a["filter_banks"], b["filter_banks"], strict=True):
        np.testing.assert_allclose(bank_a.kernel, bank_b.kernel, rtol=1e-6)
    normalised_flow = flow / jnp.asarray([32.0, 24.0]) * normalised.flow_scale
    np.testing.assert_allclose(
        a["inv_depth"], _local_network_by_hand(variables, a["filter_banks"], flow), rtol=1e-4
    )
    np.testing.assert_allclose(
        b["inv_depth"],
        _local_network_by_hand(variables, b["filter_banks"], normalised_flow),
        rtol=1e-4,
    )
    assert not np.allclose(a["inv_depth"], b["inv_depth"], rtol=1e-3)
    with pytest.raises(ValueError, match="local_flow_units"):
        jax.eval_shape(
            model_lib.GlobalLocal(local_flow_units="metres").init,
            jax.random.key(0),
            image1,
            image2,
            flow,
        )


def test_flow_scale_multiplies_the_flow_both_modules_see(paper_model):
    # flow_scale changes no parameter: the paper model's variables serve both.
    scaled, variables, (image1, image2, flow), apply_scaled = paper_model
    assert scaled.flow_scale == 10.0
    plain = jax.jit(model_lib.GlobalLocal(flow_scale=1.0).apply)
    a = apply_scaled(variables, image1, image2, flow)
    b = plain(variables, image1, image2, flow * 10.0)
    np.testing.assert_allclose(a["inv_depth"], b["inv_depth"], rtol=1e-5)
    np.testing.assert_allclose(a["global_params"], b["global_params"], rtol=1e-5, atol=1e-7)
    c = plain(variables, image1, image2, flow)
    assert not np.allclose(a["global_params"], c["global_params"])


@pytest.mark.slow  # global_norm="batch": an option no recipe uses
def test_batch_normalised_global_params_vary_across_pairs_from_initialisation():
    image1, image2, flow = _inputs(batch=8)
    spread = {}
    for norm in ("none", "batch"):
        model = model_lib.GlobalLocal(global_norm=norm)
        variables = model.init(jax.random.key(0), image1, image2, flow)
        outputs, _ = model.apply(
            variables, image1, image2, flow, train=True, mutable=["batch_stats"]
        )
        spread[norm] = np.asarray(outputs["global_params"]).std(axis=0)
    # The pooled encoder output barely differs between pairs; standardised, every
    # global parameter has unit spread over the batch, so it steers the filters.
    assert spread["none"].max() < 0.1
    np.testing.assert_allclose(spread["batch"], 1.0, rtol=0.02)


@pytest.mark.slow  # global_norm="batch": an option no recipe uses
def test_batch_normalised_global_params_use_running_statistics_at_test_time():
    image1, image2, flow = _inputs(batch=4)
    model = model_lib.GlobalLocal(global_norm="batch")
    variables = model.init(jax.random.key(0), image1, image2, flow)
    assert set(variables["batch_stats"]["global_norm"]) == {"mean", "var"}
    # Test time: one pair alone gets the same parameters as inside its batch.
    alone = model.apply(variables, image1[:1], image2[:1], flow[:1])
    together = model.apply(variables, image1, image2, flow)
    np.testing.assert_allclose(
        alone["global_params"][0], together["global_params"][0], rtol=1e-4, atol=1e-6
    )
    _, updates = model.apply(variables, image1, image2, flow, train=True, mutable=["batch_stats"])
    moved = updates["batch_stats"]["global_norm"]["mean"]
    assert not np.allclose(moved, variables["batch_stats"]["global_norm"]["mean"])
    with pytest.raises(ValueError, match="global_norm"):
        model_lib.GlobalLocal(global_norm="layer").init(jax.random.key(0), image1, image2, flow)


def test_given_pose_global_parameters_are_the_rotation_vector_part_and_translation_direction():
    from gld import geometry

    axis_angle = np.array([[0.0, 0.1, 0.0], [0.05, -0.02, 0.03]])
    rotation = jnp.asarray(geometry.rotation_matrix(axis_angle), jnp.float32)
    translation = jnp.asarray([[0.0, 0.0, 2.0], [3.0, 4.0, 0.0]], jnp.float32)
    params = np.asarray(model_lib.pose_parameters(rotation, translation))
    angle = np.linalg.norm(axis_angle, axis=-1, keepdims=True)
    expected_rotation = model_lib.POSE_ROTATION_SCALE * np.sin(angle) * axis_angle / angle
    np.testing.assert_allclose(params[:, :3], expected_rotation, atol=1e-6)
    np.testing.assert_allclose(params[:, 3:], [[0, 0, 1], [0.6, 0.8, 0]], atol=1e-6)
    with pytest.raises(ValueError, match="rotation must be"):
        model_lib.pose_parameters(rotation[0], translation)
    with pytest.raises(ValueError, match="translation must be"):
        model_lib.pose_parameters(rotation, translation[:, :2])


def test_a_model_given_the_pose_steers_its_filters_with_it_and_has_no_encoder():
    from gld import geometry
    from gld.runs import state

    image1, image2, flow = _inputs(batch=2)
    rotation = jnp.asarray(geometry.rotation_matrix(np.array([[0.0, 0.1, 0.0]] * 2)), jnp.float32)
    translation = jnp.asarray([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0]], jnp.float32)
    model = model_lib.GlobalLocal(global_source="pose")
    assert model.extra_inputs == ("rotation", "translation")
    assert model_lib.GlobalLocal().extra_inputs == ()
    variables = state.init_variables(model, 24, 32, seed=0)
    assert set(variables["params"]) == {"hypernet", "final_conv"}
    apply = jax.jit(model.apply)
    outputs = apply(variables, image1, image2, flow, rotation=rotation, translation=translation)
    np.testing.assert_allclose(
        outputs["global_params"], model_lib.pose_parameters(rotation, translation), atol=1e-6
    )
    # Each pair's filters are the hypernetwork's linear map of its pose parameters, and
    # its depth the local network's with those filters; with the translations swapped,
    # the pairs' filters swap.
    for given_translation in (translation, translation[::-1]):
        given = apply(
            variables, image1, image2, flow, rotation=rotation, translation=given_translation
        )
        expected = reference.global_local(
            model,
            variables,
            *(np.asarray(x) for x in (image1, image2, flow)),
            global_params=np.asarray(model_lib.pose_parameters(rotation, given_translation)),
        )
        for bank, (kernel, bias) in zip(given["filter_banks"], expected["banks"], strict=True):
            np.testing.assert_allclose(bank.kernel, kernel, rtol=1e-4, atol=1e-5)
            np.testing.assert_allclose(bank.bias, bias, rtol=1e-4, atol=1e-5)
        np.testing.assert_allclose(given["inv_depth"], expected["inv_depth"], rtol=1e-4)
    np.testing.assert_allclose(
        given["filter_banks"][0].kernel[::-1], outputs["filter_banks"][0].kernel, rtol=1e-6
    )
    with pytest.raises(ValueError, match="needs the relative pose"):
        model.apply(variables, image1, image2, flow)
    with pytest.raises(ValueError, match="global_dim is 4"):
        model_lib.GlobalLocal(global_source="pose", global_dim=4).init(
            jax.random.key(0), image1, image2, flow, rotation=rotation, translation=translation
        )
    with pytest.raises(ValueError, match="global_dim is 4"):
        registry.check_config("global_local", {"global_source": "pose", "global_dim": 4})
    with pytest.raises(ValueError, match="global_source must be one of"):
        registry.check_config("global_local", {"global_source": "imu"})


def test_global_params_read_as_a_pose_invert_the_given_pose_parameters():
    from gld import geometry

    axis_angle = np.array([[0.0, 0.1, 0.0], [0.05, -0.02, 0.03]])
    rotation = jnp.asarray(geometry.rotation_matrix(axis_angle), jnp.float32)
    translation = jnp.asarray([[0.0, 0.0, 1.0], [0.6, 0.8, 0.0]], jnp.float32)
    pose = model_lib.global_params_pose(model_lib.pose_parameters(rotation, translation))
    # sin(angle) is read back as the angle: exact to third order in the angle.
    errors = geometry.rotation_error_degrees(np.asarray(pose["rotation"]), np.asarray(rotation))
    assert np.max(errors) < 0.01
    np.testing.assert_allclose(pose["translation"], translation, atol=1e-6)
    # Finite gradients at g = 0 (no rotation).
    gradient = jax.grad(lambda g: jnp.sum(model_lib.global_params_pose(g)["rotation"]))(
        jnp.zeros((1, 6))
    )
    assert np.all(np.isfinite(gradient))
    image1, image2, flow = _inputs()
    for global_dim, has_pose in ((6, True), (4, False)):
        outputs, _ = jax.eval_shape(
            model_lib.GlobalLocal(global_dim=global_dim).init_with_output,
            jax.random.key(0),
            image1,
            image2,
            flow,
        )
        assert ("global_pose" in outputs) == has_pose
        if has_pose:
            assert outputs["global_pose"]["rotation"].shape == (2, 3, 3)


# The first entries of `gld.models.global_local._PERTURBATION_MIX` when the pose-error runs of
# WORKSPACE.md were made.
PINNED_PERTURBATION_MIX = [12.57302188873291, -13.21048641204834, 64.04226684570312]


def test_a_perturbed_pose_is_off_by_exactly_the_given_angles_the_same_way_each_time():
    from gld import geometry
    from gld.analysis import probes

    rng = np.random.default_rng(3)
    rotation = jnp.asarray(geometry.rotation_matrix(rng.normal(0, 0.05, (64, 3))), jnp.float32)
    translation = jnp.asarray(rng.normal(0, 1, (64, 3)) * 2.5, jnp.float32)
    off_rotation, off_translation = model_lib.perturbed_pose(rotation, translation, 0.5, 6.0)
    rotation_error = geometry.rotation_error_degrees(
        np.asarray(off_rotation, np.float64), np.asarray(rotation, np.float64)
    )
    np.testing.assert_allclose(rotation_error, 0.5, atol=0.02)
    translation_error = geometry.translation_error_degrees(
        np.asarray(off_translation, np.float64), np.asarray(translation, np.float64)
    )
    np.testing.assert_allclose(translation_error, 6.0, atol=0.02)
    np.testing.assert_allclose(
        np.linalg.norm(off_translation, axis=-1), np.linalg.norm(translation, axis=-1), rtol=1e-5
    )
    # A pair's error is a function of its own pose, whatever else is in the batch.
    order = rng.permutation(64)
    shuffled = model_lib.perturbed_pose(rotation[order], translation[order], 0.5, 6.0)
    np.testing.assert_allclose(shuffled[0], off_rotation[order], atol=1e-5)
    np.testing.assert_allclose(shuffled[1], off_translation[order], atol=1e-5)
    alone = model_lib.perturbed_pose(rotation[5:6], translation[5:6], 0.5, 6.0)
    np.testing.assert_allclose(alone[0][0], off_rotation[5], atol=1e-5)
    np.testing.assert_allclose(alone[1][0], off_translation[5], atol=1e-5)
    # Different poses are off in different directions.
    relative = np.asarray(off_rotation @ jnp.swapaxes(rotation, 1, 2), np.float64)
    axes = probes.rotation_vector(relative)
    axes /= np.linalg.norm(axes, axis=-1, keepdims=True)
    assert np.all(np.abs(axes.mean(axis=0)) < 0.3), axes.mean(axis=0)
    turn_axes = np.cross(np.asarray(translation), np.asarray(off_translation))
    turn_axes /= np.linalg.norm(turn_axes, axis=-1, keepdims=True)
    np.testing.assert_allclose(np.sum(turn_axes * np.asarray(translation), -1), 0.0, atol=1e-4)
    assert np.all(np.abs(turn_axes.mean(axis=0)) < 0.3), turn_axes.mean(axis=0)
    # The mixing that fixes the directions is pinned: runs stay comparable across releases.
    np.testing.assert_allclose(
        model_lib._PERTURBATION_MIX[0, :3], PINNED_PERTURBATION_MIX, rtol=1e-6
    )
    unchanged = model_lib.perturbed_pose(rotation, translation, 0.0, 0.0)
    np.testing.assert_allclose(unchanged[0], rotation, atol=1e-6)
    np.testing.assert_allclose(unchanged[1], translation, atol=1e-6)


def test_a_model_given_a_perturbed_pose_reads_it_and_refuses_it_without_a_given_pose():
    from gld import geometry
    from gld.runs import state

    image1, image2, flow = _inputs(batch=2)
    rotation = jnp.asarray(geometry.rotation_matrix(np.array([[0.0, 0.1, 0.0]] * 2)), jnp.float32)
    translation = jnp.asarray([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0]], jnp.float32)
    model = model_lib.GlobalLocal(
        global_source="pose", pose_rotation_error=2.0, pose_translation_error=10.0
    )
    variables = state.init_variables(model, 24, 32, seed=0)
    outputs = model.apply(
        variables, image1, image2, flow, rotation=rotation, translation=translation
    )
    expected = model_lib.pose_parameters(
        *model_lib.perturbed_pose(rotation, translation, 2.0, 10.0)
    )
    np.testing.assert_allclose(outputs["global_params"], expected, atol=1e-6)
    assert not np.allclose(
        outputs["global_params"], model_lib.pose_parameters(rotation, translation)
    )
    registry.check_config("global_local", {"global_source": "pose", "pose_rotation_error": 0.5})
    with pytest.raises(ValueError, match="pose_rotation_error is the error of a given pose"):
        registry.check_config("global_local", {"pose_rotation_error": 0.5})
    with pytest.raises(ValueError, match="pose_translation_error must be at least 0"):
        registry.check_config(
            "global_local", {"global_source": "pose", "pose_translation_error": -1.0}
        )
    with pytest.raises(ValueError, match="at most 180"):
        registry.check_config("global_local", {"global_source": "pose", "pose_rotation_error": 200})


def test_encoder_norm_reaches_the_global_encoder_and_old_configs_read_as_unnormalised():
    image1, image2, flow = _inputs()

    def encoder_layers(norm):
        model = model_lib.GlobalLocal(encoder_norm=norm)
        variables = jax.eval_shape(model.init, jax.random.key(0), image1, image2, flow)
        return set(variables["params"]["global_encoder"])

    assert {f"norm{i}" for i in range(5)} <= encoder_layers("instance")
    assert not any(name.startswith("norm") for name in encoder_layers("none"))
    # A stored config written before the option was trained without normalisation.
    assert registry.complete_stored_config("global_local", {})["encoder_norm"] == "none"
    with pytest.raises(ValueError, match="encoder_norm must be one of"):
        registry.check_config("global_local", {"encoder_norm": "layer"})


@pytest.mark.slow
def test_encoder_coordinates_reach_the_global_encoder_alone():
    from gld import geometry

    image1, image2, flow = _inputs()
    with_coordinates = model_lib.GlobalLocal(use_image_pair=False, encoder_coordinates=True)
    variables = _init(with_coordinates, image1, image2, flow)
    # The flow (2 channels) and x, y: the encoder's first kernel reads 4 channels.
    assert variables["params"]["global_encoder"]["conv0"]["kernel"].shape[2] == 4
    outputs = jax.jit(with_coordinates.apply)(variables, image1, image2, flow)
    # The encoder's output is its own applied to the flow with the coordinates appended.
    coordinates = jnp.broadcast_to(
        geometry.normalised_coordinates(24, 32, jnp), (2, 24, 32, 2)
    ).astype(jnp.float32)
    encoder_inputs = jnp.concatenate([layers.normalise_flow(flow) * 10.0, coordinates], -1)
    expected = jax.jit(model_lib.GlobalEncoder().apply)(
        {"params": variables["params"]["global_encoder"]}, encoder_inputs
    )
    np.testing.assert_allclose(outputs["global_params"], expected, rtol=1e-5, atol=1e-7)
    # The local network's input is unchanged: flow and coordinates.
    plain = jax.eval_shape(
        model_lib.GlobalLocal(use_image_pair=False).init, jax.random.key(0), image1, image2, flow
    )
    assert plain["params"]["global_encoder"]["conv0"]["kernel"].shape[2] == 2
    assert jax.tree_util.tree_map(jnp.shape, plain["params"]["hypernet"]) == jax.tree_util.tree_map(
        jnp.shape, variables["params"]["hypernet"]
    )
    # A stored config written before the option had no coordinates in the encoder.
    assert registry.complete_stored_config("global_local", {})["encoder_coordinates"] is False


@pytest.fixture(scope="module")
def model_without_coordinates():
    """The paper's model without CoordConv (whose depth varies across a uniform input)."""
    model = model_lib.GlobalLocal(use_coordinates=False)
    return model, _init(model, *_inputs())


@pytest.mark.parametrize("formulation", ["fused", "shifted", "vmap"])
def test_an_edge_border_gives_a_uniform_input_a_uniform_depth_map(
    model_without_coordinates, formulation
):
    """Zero padding makes the outermost pixels differ from their neighbours (a rim in
    every depth map); repeating the input's edge does not, and the interior is the same."""
    model, variables = model_without_coordinates
    height, width = 24, 32
    image = jnp.full((1, height, width, 3), 0.1, jnp.float32)
    flow = jnp.broadcast_to(jnp.float32([2.0, -1.0]), (1, height, width, 2))

    def inv_depth(border):
        bordered = model.clone(border=border, filter_formulation=formulation)
        return np.asarray(bordered.apply(variables, image, image, flow)["inv_depth"][0])

    zero, edge = inv_depth("zero"), inv_depth("edge")
    assert np.ptp(zero) > 1e-5 and np.ptp(zero[4:-4, 4:-4]) < 1e-6  # the rim
    assert np.ptp(edge) < 1e-6
    np.testing.assert_allclose(edge, zero[height // 2, width // 2], rtol=1e-6)
    # A stored config written before the option had the zero border.
    assert registry.complete_stored_config("global_local", {})["border"] == "zero"
    with pytest.raises(ValueError, match="border must be one of"):
        registry.check_config("global_local", {"border": "reflect"})
