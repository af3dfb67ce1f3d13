"""Tests of gld/models/flow_depth.py and the learned flow estimator: the flow network inside a
depth model (frozen or fine-tuned), its pretrained start, the conv-head model, and a
trained network as the stored flow of a dataset build.

The flow network inside a depth model is an option no main recipe uses: the tests that
compile or train it (20-30 s each on the 2-core CPU) are slow; the default run keeps the
checks of the options and the refusals."""

import jax
import numpy as np
import optax
import pytest
from conftest import random_variables

from gld import flow
from gld.losses import supervised as losses
from gld.models import flow_depth, registry
from gld.models.flow_net import FlowNet
from gld.runs import flow_config, trained_flow
from gld.training import flow_trainer as flow_training

HEIGHT, WIDTH = 32, 48


def _inputs(seed=0, batch=2):
    rng = np.random.default_rng(seed)
    image1 = rng.uniform(-0.5, 0.5, (batch, HEIGHT, WIDTH, 3)).astype(np.float32)
    image2 = np.roll(image1, 2, axis=2)
    flow_given = np.zeros((batch, HEIGHT, WIDTH, 2), np.float32)
    return image1, image2, flow_given


def _sparse_batch(seed=0, batch=2):
    image1, image2, flow_given = _inputs(seed, batch)
    rng = np.random.default_rng(seed + 1)
    mask = np.zeros((batch, HEIGHT, WIDTH), np.float32)
    mask[:, HEIGHT // 2, WIDTH // 3] = 1.0
    return {
        "image1": image1,
        "image2": image2,
        "flow": flow_given,
        "depth": rng.uniform(1.0, 5.0, (batch, HEIGHT, WIDTH)).astype(np.float32),
        "sparse_mask": mask,
    }


@pytest.fixture(scope="module")
def flow_run(tiny_scenes, tmp_path_factory):
    """A flow network (FlowNet's default architecture) trained for 2 steps on
    gld_scenes/tiny, in a workdir as `experiments.train_flow` leaves it."""
    workdir = tmp_path_factory.mktemp("flow_run")
    config = flow_config.FlowTrainConfig(
        dataset="gld_scenes/tiny",
        height=48,
        width=64,
        batch_size=2,
        steps=2,
        warmup_steps=1,
        eval_every=0,
        checkpoint_every=2,
        log_every=1,
    )
    flow_training.train_flow(
        config,
        workdir,
        tiny_scenes.as_data_source("train"),
        progress=False,
        print_fn=lambda _: None,
    )
    return workdir


def _sparse_gradients(depth_model, params, batch):
    def loss(params):
        outputs = depth_model.apply(
            {"params": params}, batch["image1"], batch["image2"], batch["flow"]
        )
        return losses.total_loss(outputs, batch, losses.LossWeights())[0]

    return jax.jit(jax.grad(loss))(params)


@pytest.mark.slow
@pytest.mark.parametrize("trainable", [False, True])
def test_the_switch_freezes_or_fine_tunes_the_flow_network(trainable):
    depth_model = flow_depth.GlobalLocalFlowNet(flow_trainable=trainable)
    params = random_variables(depth_model, HEIGHT, WIDTH, seed=0)["params"]
    grads = _sparse_gradients(depth_model, params, _sparse_batch())
    flow_norm = float(optax.global_norm(grads["flow_net"]))
    assert float(optax.global_norm(grads["global_local"])) > 0
    if trainable:
        assert flow_norm > 0
    else:
        assert flow_norm == 0.0


@pytest.mark.slow
def test_the_models_compute_their_own_flow_and_ignore_the_given_one():
    image1, image2, flow_given = _inputs()
    for depth_model in (flow_depth.GlobalLocalFlowNet(), flow_depth.FlowNetHead()):
        variables = random_variables(depth_model, HEIGHT, WIDTH, seed=1)
        apply = jax.jit(depth_model.apply)
        outputs = apply(variables, image1, image2, flow_given)
        other = apply(variables, image1, image2, flow_given + 5.0)
        assert outputs["depth"].shape == outputs["inv_depth"].shape == (2, HEIGHT, WIDTH)
        np.testing.assert_array_equal(outputs["depth"], other["depth"])
        expected = FlowNet().apply({"params": variables["params"]["flow_net"]}, image1, image2)[
            "flow"
        ]
        np.testing.assert_allclose(outputs["flow"], expected, rtol=1e-5, atol=1e-5)
        assert np.all(np.asarray(outputs["inv_depth"]) > 0)


def test_the_head_is_three_convolutions_ending_in_one_channel():
    image1, image2, flow_given = _inputs(batch=1)
    params = jax.eval_shape(
        flow_depth.FlowNetHead().init, jax.random.key(0), image1, image2, flow_given
    )["params"]
    kernels = [params[f"head{i}"]["kernel"].shape for i in range(3)]
    assert kernels == [(3, 3, 2, 32), (3, 3, 32, 16), (3, 3, 16, 1)]
    with pytest.raises(ValueError, match="head_channels must end with 1"):
        jax.eval_shape(
            flow_depth.FlowNetHead(head_channels=(8, 4)).init,
            jax.random.key(0),
            image1,
            image2,
            flow_given,
        )


@pytest.mark.slow
def test_pretrained_parameters_are_the_flow_runs(flow_run):
    depth_model = flow_depth.GlobalLocalFlowNet(flow_net_workdir=str(flow_run))
    image1, image2, _ = _inputs()
    params = random_variables(depth_model, HEIGHT, WIDTH, seed=0)["params"]
    loaded, note = trained_flow.load_pretrained_flow(params, depth_model.flow_net_workdir)
    _, variables, _, step = trained_flow.load_flow_run(flow_run)
    assert step == 2 and "step 2" in note and str(flow_run) in note
    jax.tree.map(np.testing.assert_array_equal, loaded["flow_net"], variables["params"])
    jax.tree.map(np.testing.assert_array_equal, loaded["global_local"], params["global_local"])
    assert trained_flow.load_pretrained_flow(params, "") is None

    smaller = jax.eval_shape(
        lambda: FlowNet(feature_channels=(8, 8, 8, 8)).init(jax.random.key(0), image1, image2)
    )["params"]
    with pytest.raises(ValueError, match="another architecture"):
        trained_flow.load_pretrained_flow({**params, "flow_net": smaller}, str(flow_run))


def test_the_global_local_options_reach_the_inner_model():
    image1, image2, flow_given = _inputs(batch=1)

    def encoder(**options):
        depth_model = flow_depth.GlobalLocalFlowNet(global_local=options)
        params = jax.eval_shape(depth_model.init, jax.random.key(0), image1, image2, flow_given)
        return params["params"]["global_local"]["global_encoder"]

    # The main recipe: an encoder on the flow alone (2 channels), instance-normalised.
    recipe = encoder(
        use_image_pair=False, encoder_norm="instance", encoder_channels=[4, 8, 8, 8, 8]
    )
    assert recipe["conv0"]["kernel"].shape[-2:] == (2, 4) and "norm0" in recipe
    default = encoder()
    assert default["conv0"]["kernel"].shape[-2] == 8 and "norm0" not in default
    with pytest.raises(ValueError, match="global_local: encoder_norm must be one of"):
        registry.check_config("global_local_flow_net", {"global_local": {"encoder_norm": "x"}})
    # A run stored before the option existed was trained with the defaults.
    assert registry.complete_stored_config("global_local_flow_net", {})["global_local"] == {}


def test_a_missing_flow_run_is_refused_when_the_config_is_checked(tmp_path):
    with pytest.raises(ValueError, match="holds no flow-network run"):
        registry.check_config("global_local_flow_net", {"flow_net_workdir": str(tmp_path)})
    registry.check_config("flow_net_head", {"flow_net_workdir": ""})


@pytest.mark.slow
def test_a_trained_network_is_a_flow_estimator(flow_run, eval_batch):
    method = flow.LEARNED_PREFIX + str(flow_run)
    flow.check_estimator(method)
    image1 = eval_batch["image1"][0]
    image2 = eval_batch["image2"][0]
    as_uint8 = [np.rint((image + 0.5) * 255).astype(np.uint8) for image in (image1, image2)]
    estimated = trained_flow.estimate_flow(*as_uint8, method=method)
    _, variables, _, _ = trained_flow.load_flow_run(flow_run)
    expected = jax.jit(FlowNet().apply)(variables, image1[None], image2[None])["flow"][0]
    assert estimated.shape == (48, 64, 2) and estimated.dtype == np.float32
    np.testing.assert_allclose(estimated, expected, atol=1e-3)
    described = trained_flow.describe_flow(method)
    assert described["step"] == 2
    assert described["params_sha256"] == trained_flow.params_digest(variables["params"])
    with pytest.raises(ValueError, match="unknown flow estimator 'pwc'"):
        flow.check_estimator("pwc")
    # The classical estimators' module never loads a network: it names the one that does.
    with pytest.raises(ValueError, match="trained_flow.estimate_flow"):
        flow.estimate(*as_uint8, method=method)
    np.testing.assert_array_equal(
        trained_flow.estimate_flow(*as_uint8, method="dis"), flow.estimate(*as_uint8)
    )
    assert trained_flow.describe_flow("dis") == {"estimator": "dis"}


@pytest.mark.slow
def test_a_new_run_starts_from_the_flow_run_and_a_frozen_network_stays_there(
    flow_run, tiny_scenes, tmp_path
):
    from conftest import tiny_train_config

    from gld.runs import workdir
    from gld.training import trainer as train

    config = tiny_train_config(
        model="global_local_flow_net",
        model_config={"flow_net_workdir": str(flow_run)},
        steps=2,
        checkpoint_every=1,
    )
    notes = []
    train.train_and_evaluate(
        config, tmp_path, tiny_scenes.as_data_source("train"), progress=False, print_fn=notes.append
    )
    assert any("flow network initialised from" in note for note in notes)
    _, pretrained, _, _ = trained_flow.load_flow_run(flow_run)
    trained = workdir.load_trained(tmp_path)[1]["params"]
    jax.tree.map(np.testing.assert_array_equal, trained["flow_net"], pretrained["params"])

    # Resumed (2 more steps), the run restores its checkpoint, not the flow run.
    notes.clear()
    train.train_and_evaluate(
        tiny_train_config(
            model="global_local_flow_net",
            model_config={"flow_net_workdir": str(flow_run)},
            steps=4,
            checkpoint_every=1,
        ),
        tmp_path,
        tiny_scenes.as_data_source("train"),
        progress=False,
        print_fn=notes.append,
    )
    assert not any("flow network initialised from" in note for note in notes)


@pytest.mark.slow
def test_a_dataset_build_stores_the_trained_networks_flow(flow_run, tmp_path):
    import data

    method = flow.LEARNED_PREFIX + str(flow_run)
    builder = data.prepare("gld_scenes/tiny", tmp_path, workers=2, flow_estimator=method)
    assert builder.info.metadata["build_options"]["test"] == {"flow_estimator": method}
    assert builder.info.metadata["flow_estimator_source"]["step"] == 2
    from gld import input_pipeline

    source = builder.as_data_source("test")
    batch = next(input_pipeline.eval_batches([source[i] for i in range(2)], batch_size=2))
    network = trained_flow.TrainedFlowNet(flow_run)
    for index in range(2):
        expected = network(batch["image1"][index], batch["image2"][index])
        # The records store flow as float16.
        np.testing.assert_allclose(batch["flow"][index], expected, rtol=2e-3, atol=1e-3)
    with pytest.raises(ValueError, match="flow_estimator='dis' given, built with"):
        data.prepare("gld_scenes/tiny", tmp_path, flow_estimator="dis")
