"""Training and evaluating the flow network: the loss, the step, EPE against the truth."""

import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from gld import contract, flow
from gld.evaluation import flow_network
from gld.models import flow_net
from gld.runs import flow_config
from gld.runs import state as state_lib
from gld.runs.optimizer import make_optimizer
from gld.training import flow_trainer as flow_training

# A network small enough to train for a hundred steps in seconds at 64x48.
TINY_NET = dict(
    feature_channels=(8, 12, 16),
    estimator_channels=(16, 8),
    context_channels=(),
    max_displacement=2,
)


def _truth_outputs(gt_flow, valid, levels=(3, 2)):
    """Outputs whose every estimate is the truth at its level."""
    pyramid = [flow_training.downsample_truth(gt_flow, valid, 2**level)[0] for level in levels]
    return {"flow": gt_flow, "flow_pyramid": pyramid}


def _random_truth(shape=(2, 16, 24)):
    rng = np.random.default_rng(0)
    gt_flow = jnp.asarray(rng.normal(size=(*shape, 2)).astype(np.float32) * 3)
    valid = jnp.asarray(rng.uniform(size=shape) > 0.3)
    return gt_flow, valid


def test_downsampled_truth_averages_each_blocks_valid_pixels():
    gt_flow = np.zeros((1, 4, 4, 2), np.float32)
    gt_flow[0, :2, :2, 0] = [[1.0, 3.0], [5.0, 100.0]]  # 100 is invalid
    valid = np.ones((1, 4, 4), bool)
    valid[0, 1, 1] = False
    valid[0, 2:, 2:] = False  # a block with no valid pixel
    low, low_valid = flow_training.downsample_truth(jnp.asarray(gt_flow), jnp.asarray(valid), 2)
    assert low.shape == (1, 2, 2, 2)
    assert float(low[0, 0, 0, 0]) == pytest.approx(3.0)
    np.testing.assert_array_equal(low_valid[0], [[True, True], [True, False]])


@pytest.mark.parametrize("loss, expected", [("epe", 0.0), ("robust", 0.01**0.4)])
def test_the_loss_is_its_floor_when_every_estimate_is_the_truth(loss, expected):
    gt_flow, valid = _random_truth()
    outputs = _truth_outputs(gt_flow, valid)
    total, terms = flow_training.flow_loss(
        outputs, {"gt_flow": gt_flow, "gt_flow_valid": valid}, loss=loss, pyramid_weight=0.5
    )
    assert float(terms["full"]) == pytest.approx(expected, abs=1e-5)
    assert float(total) == pytest.approx(1.5 * expected, abs=1e-5)
    assert set(terms) == {"loss", "full", "epe", "level2", "level3"}
    assert float(terms["epe"]) == pytest.approx(0.0, abs=1e-5)


def test_the_loss_is_the_mean_end_point_error_over_valid_pixels_only():
    gt_flow, valid = _random_truth()
    outputs = _truth_outputs(gt_flow, valid)
    # 3-4-5: every valid pixel off by 5 px; invalid pixels off by anything
    offset = jnp.where(valid[..., None], jnp.float32([3.0, 4.0]), jnp.float32([50.0, -70.0]))
    outputs["flow"] = gt_flow + offset
    _, terms = flow_training.flow_loss(
        outputs, {"gt_flow": gt_flow, "gt_flow_valid": valid}, pyramid_weight=0.0
    )
    assert float(terms["full"]) == pytest.approx(5.0, rel=1e-5)
    assert float(terms["loss"]) == pytest.approx(5.0, rel=1e-5)


def test_config_validation_names_the_option():
    with pytest.raises(ValueError, match="batch_size"):
        flow_config.FlowTrainConfig(batch_size=0).validate()
    with pytest.raises(ValueError, match="loss must be one of"):
        flow_config.FlowTrainConfig(loss="l1").validate()
    with pytest.raises(ValueError, match="warmup_steps"):
        flow_config.FlowTrainConfig(steps=10, warmup_steps=10).validate()
    with pytest.raises(ValueError, match="unknown FlowNet options"):
        flow_config.FlowTrainConfig(model_config={"channels": 3}).validate()
    with pytest.raises(ValueError, match="divisible by 32"):
        flow_config.FlowTrainConfig(
            model_config={"feature_channels": [4] * 5}, height=48, width=64
        ).validate()


@pytest.fixture(scope="module")
def tiny_pairs(tiny_scenes):
    """Four training pairs of gld_scenes/tiny as one batch, with their true flow."""
    source = tiny_scenes.as_data_source("train")
    examples = [contract.decode_example(source[i], flow_source="gt") for i in range(4)]
    return {
        key: jnp.asarray(np.stack([e[key] for e in examples]))
        for key in ("image1", "image2", "gt_flow", "gt_flow_valid")
    }


def _train(batch, steps, learning_rate=2e-3):
    model = flow_net.FlowNet(**TINY_NET)
    optimizer = make_optimizer(learning_rate)
    state = state_lib.create_flow_state(model, optimizer, 48, 64, seed=0)
    step = jax.jit(flow_training.make_flow_train_step(model=model, optimizer=optimizer))
    epes = []
    for _ in range(steps):
        state, metrics = step(state, batch, jax.random.key(0))
        epes.append(float(metrics["epe"]))
    return state, epes


# The learned flow network's learning (~20 s): no main recipe trains it.
@pytest.mark.slow
def test_training_steps_lower_the_end_point_error(tiny_pairs):
    state, epes = _train(tiny_pairs, steps=60)
    assert int(state.step) == 60
    assert np.all(np.isfinite(epes))
    # the first steps' EPE is that of (nearly) zero flow
    zero_flow_epe = float(
        jnp.linalg.norm(tiny_pairs["gt_flow"], axis=-1)[tiny_pairs["gt_flow_valid"]].mean()
    )
    assert epes[0] == pytest.approx(zero_flow_epe, rel=0.3)
    assert np.mean(epes[-5:]) < 0.6 * epes[0]


@pytest.mark.slow
def test_a_few_hundred_steps_fit_the_pairs_closely(tiny_pairs):
    _, epes = _train(tiny_pairs, steps=400)
    assert np.mean(epes[-10:]) < 0.25 * epes[0]


def test_evaluation_scores_the_network_and_the_stored_flow_on_the_same_pixels(
    tiny_scenes, tmp_path
):
    source = tiny_scenes.as_data_source("test")
    model = flow_net.FlowNet(**TINY_NET)
    variables = {"params": flow_net.init_params(model, seed=0)}
    # 5 does not divide the 16 pairs: the padded rows must not count
    per_example, ids, summary = flow_network.evaluate_flow(model, variables, source, batch_size=5)
    assert len(ids) == 20 and int(per_example["example_mask"].sum()) == 16
    assert summary["dis"]["count"] == summary["flow_net"]["count"] == 16
    # the stored flow's EPE, pair by pair, as gld.flow computes it
    expected = []
    for index in range(len(source)):
        example = contract.decode_example(source[index])
        expected.append(
            flow.endpoint_error(example["flow"], example["gt_flow"], example["gt_flow_valid"])
        )
    mask = per_example["example_mask"]
    np.testing.assert_allclose(per_example["dis_epe"][mask], expected, rtol=1e-5)
    assert summary["dis"]["epe"] == pytest.approx(np.mean(expected), rel=1e-5)
    # the untrained network predicts nearly zero flow: its EPE is about the flow's size
    assert summary["flow_net"]["epe"] > summary["dis"]["epe"]
    assert 0.0 <= summary["flow_net"]["outliers"] <= 1.0

    latency = flow_network.forward_latency(model, variables, 48, 64, repeats=3)
    assert latency["median_ms"] > 0 and latency["repeats"] == 3
    table = flow_network.write_flow_report(
        tmp_path / "eval",
        summary,
        parameters=flow_net.parameter_count(variables["params"]),
        latency=latency,
        info={"dataset": "gld_scenes/tiny", "split": "test", "step": 0, "height": 48, "width": 64},
    )
    report = json.loads((tmp_path / "eval" / "flow.json").read_text())
    assert report["methods"]["dis"]["epe"] == pytest.approx(summary["dis"]["epe"])
    assert report["epe_vs_dis"] == pytest.approx(summary["flow_net"]["epe"] / summary["dis"]["epe"])
    assert report["parameters"] == flow_net.parameter_count(variables["params"])
    assert (tmp_path / "eval" / "flow_table.md").read_text() == table
    assert "| dis (stored estimated flow, OpenCV DIS) |" in table
    assert f"| {summary['dis']['epe']:.3f} |" in table


def test_a_workdir_of_another_run_is_refused(tmp_path):
    config = flow_config.FlowTrainConfig(dataset="gld_scenes/tiny", height=48, width=64)
    assert flow_training.check_flow_workdir(tmp_path, config) == {}
    flow_training.write_flow_config(tmp_path, config)
    longer = flow_config.FlowTrainConfig(dataset="gld_scenes/tiny", height=48, width=64, steps=6000)
    assert flow_training.check_flow_workdir(tmp_path, longer) == {"steps": (5000, 6000)}
    other = flow_config.FlowTrainConfig(
        dataset="gld_scenes/tiny", height=48, width=64, model_config={"max_displacement": 3}
    )
    with pytest.raises(ValueError, match="model_config.max_displacement: 4 in the workdir vs 3"):
        flow_training.check_flow_workdir(tmp_path, other)
    depth_run = tmp_path / "depth"
    depth_run.mkdir()
    (depth_run / "config.json").write_text("{}")
    with pytest.raises(ValueError, match="holds a depth run"):
        flow_training.check_flow_workdir(depth_run, config)
