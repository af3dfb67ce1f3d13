"""Tests of gld/analysis/probes.py: pair statistics, rotation vectors, the pose probes, collect."""

import itertools

import jax
import numpy as np
import pytest
from conftest import random_variables

from gld import contract, geometry, input_pipeline
from gld.analysis import encoder_pose, probes
from gld.models import global_local as model_lib
from gld.models import layers, registry


def test_rotation_vector_inverts_rodrigues():
    rng = np.random.default_rng(0)
    axis = rng.normal(size=(20, 3))
    axis /= np.linalg.norm(axis, axis=-1, keepdims=True)
    angles = rng.uniform(0.0, 3.0, size=(20, 1))
    vectors = axis * angles
    vectors[0] = 0.0  # the identity
    recovered = probes.rotation_vector(geometry.rotation_matrix(vectors))
    np.testing.assert_allclose(recovered, vectors, atol=1e-9)


def _collected(pred_mean, true_mean, pred_std, true_std, correlation, global_params=None):
    collected = {
        "pred_mean": np.asarray(pred_mean, float),
        "true_mean": np.asarray(true_mean, float),
        "pred_std": np.asarray(pred_std, float),
        "true_std": np.asarray(true_std, float),
        "correlation": np.asarray(correlation, float),
    }
    if global_params is not None:
        collected["global_params"] = np.asarray(global_params, float)
    return collected


def test_depth_statistics_on_hand_made_pairs():
    # Predicted means are half the truth's: perfectly correlated, half the spread.
    collected = _collected(
        pred_mean=[0.05, 0.10, 0.15],
        true_mean=[0.1, 0.2, 0.3],
        pred_std=[0.0, 0.01, 0.03],
        true_std=[0.02, 0.02, 0.02],
        correlation=[0.1, 0.5, 0.9],
        global_params=[[0.0, 1.0], [2.0, 1.0], [4.0, 1.0]],
    )
    statistics = probes.depth_statistics(collected)
    assert statistics["pair_scale_correlation"] == pytest.approx(1.0)
    assert statistics["pair_scale_ratio"] == pytest.approx(0.5)
    assert statistics["within_pair_correlation"] == pytest.approx(0.5)
    assert statistics["within_pair_std_ratio"] == pytest.approx(0.5)
    # std of [0, 2, 4] is sqrt(8/3); the second parameter never varies.
    assert statistics["global_params_std"] == pytest.approx(np.sqrt(8 / 3) / 2)


def test_depth_statistics_of_a_constant_prediction():
    collected = _collected([0.1] * 3, [0.1, 0.2, 0.3], [0.0] * 3, [0.02] * 3, [0.0] * 3)
    statistics = probes.depth_statistics(collected)
    assert statistics["pair_scale_correlation"] == 0.0
    assert statistics["pair_scale_ratio"] == pytest.approx(0.0, abs=1e-12)
    assert statistics["within_pair_std_ratio"] == 0.0
    assert "global_params_std" not in statistics


def test_pair_statistics_use_valid_pixels_only():
    pred = np.array([[[1.0, 2.0], [3.0, 100.0]], [[1.0, 1.0], [1.0, 1.0]]])
    true = np.array([[[2.0, 4.0], [6.0, -5.0]], [[1.0, 2.0], [3.0, 4.0]]])
    valid = np.array([[[True, True], [True, False]], [[True, False], [False, False]]])
    stats = probes.pair_statistics(pred, true, valid)
    assert stats["pred_mean"][0] == pytest.approx(2.0)
    assert stats["true_mean"][0] == pytest.approx(4.0)
    assert stats["true_std"][0] == pytest.approx(np.std([2.0, 4.0, 6.0]))
    assert stats["correlation"][0] == pytest.approx(1.0)
    # One valid pixel carries no statistics.
    assert np.isnan(stats["correlation"][1])


def _pose_pairs(rng, count, informative):
    rotation_vector = rng.normal(scale=0.1, size=(count, 3))
    translation = rng.normal(size=(count, 3))
    translation /= np.linalg.norm(translation, axis=-1, keepdims=True)
    if informative:
        # Global parameters = a fixed linear mix of the pose.
        mix = np.random.default_rng(123).normal(size=(6, 6))
        features = np.concatenate([rotation_vector, translation], -1) @ mix
    else:
        features = rng.normal(size=(count, 6))
    return {
        "global_params": features,
        "rotation_vector": rotation_vector,
        "translation": translation,
    }


def test_pose_probe_reads_the_pose_from_informative_parameters():
    rng = np.random.default_rng(0)
    train, test = _pose_pairs(rng, 256, True), _pose_pairs(rng, 64, True)
    errors = probes.pose_probe(train, test, hidden=(32, 32), steps=600, learning_rate=3e-3)
    assert errors["probe"]["rotation_deg"] < 0.5 * errors["mean_pose"]["rotation_deg"]
    assert errors["probe"]["translation_deg"] < 0.5 * errors["mean_pose"]["translation_deg"]


def test_pose_probe_finds_nothing_in_noise():
    rng = np.random.default_rng(1)
    train, test = _pose_pairs(rng, 256, False), _pose_pairs(rng, 64, False)
    errors = probes.pose_probe(train, test, hidden=(32, 32), steps=300, learning_rate=3e-3)
    # No information: the probe cannot beat the mean pose by much (it over-fits noise).
    assert errors["probe"]["translation_deg"] > 0.9 * errors["mean_pose"]["translation_deg"]


def test_pose_probe_needs_global_parameters():
    rng = np.random.default_rng(2)
    pairs = _pose_pairs(rng, 8, True)
    del pairs["global_params"]
    with pytest.raises(ValueError, match="no global parameters"):
        probes.pose_probe(pairs, pairs, steps=1)


def test_global_params_read_as_a_pose_score_zero_for_the_pose_and_ignore_the_sign_of_t():
    rng = np.random.default_rng(3)
    pairs = _pose_pairs(rng, 16, False)
    pairs["rotation_vector"] *= 0.3  # a few degrees, as on the benchmark
    rotation = geometry.rotation_matrix(pairs["rotation_vector"])
    exact = np.asarray(model_lib.pose_parameters(rotation, pairs["translation"]))
    # The rotation's vector part is read back to first order in the angle.
    errors = probes.global_params_pose_errors({**pairs, "global_params": exact})
    assert errors["rotation_deg"] < 0.01 and errors["translation_deg"] < 1e-3
    flipped = exact * np.array([1, 1, 1, -3, -3, -3])
    errors = probes.global_params_pose_errors({**pairs, "global_params": flipped})
    assert errors["translation_deg"] < 1e-3
    # A known error: a 90-degree turn of every translation about an axis normal to it.
    normal = np.cross(pairs["translation"], rng.normal(size=(16, 3)))
    turned = np.concatenate([exact[:, :3], normal], axis=-1)
    errors = probes.global_params_pose_errors({**pairs, "global_params": turned})
    np.testing.assert_allclose(errors["translation_deg"], 90.0, atol=1e-6)
    no_rotation = np.concatenate([np.zeros((16, 3)), exact[:, 3:]], axis=-1)
    errors = probes.global_params_pose_errors({**pairs, "global_params": no_rotation})
    angles = np.degrees(np.linalg.norm(pairs["rotation_vector"], axis=-1))
    np.testing.assert_allclose(errors["rotation_deg"], angles.mean(), rtol=1e-6)
    with pytest.raises(ValueError, match="six global parameters"):
        probes.global_params_pose_errors({**pairs, "global_params": exact[:, :4]})


def test_collect_reads_every_pair_once(tiny_scenes):
    source = tiny_scenes.as_data_source("test")

    def apply_fn(batch):
        # An oracle that predicts the true inverse depth, and "global params" = translation.
        depth = np.asarray(batch["depth"])
        inv_depth = np.where(depth > 0, 1.0 / np.where(depth > 0, depth, 1.0), 0.5)
        return {"inv_depth": inv_depth, "global_params": np.asarray(batch["translation"])}

    collected = probes.collect(apply_fn, source, batch_size=5, max_examples=7)
    assert collected["pred_mean"].shape == (7,)
    assert collected["global_params"].shape == (7, 3)
    # The first 7 pairs, in order, once each (the 3 padding rows of batch 2 dropped).
    translations = [contract.decode_example(source[i])["translation"] for i in range(7)]
    expected = np.stack([t / np.linalg.norm(t) for t in translations])
    np.testing.assert_allclose(collected["translation"], expected, atol=1e-6)
    np.testing.assert_allclose(collected["pred_mean"], collected["true_mean"], rtol=1e-6)
    np.testing.assert_allclose(collected["correlation"], 1.0, atol=1e-6)
    np.testing.assert_allclose(np.linalg.norm(collected["translation"], axis=-1), 1.0, atol=1e-5)
    np.testing.assert_allclose(collected["global_params"], collected["translation"], atol=1e-6)
    assert probes.depth_statistics(collected)["pair_scale_correlation"] == pytest.approx(1.0)


def test_the_encoder_trained_on_the_pose_is_scored_against_the_test_pairs_mean_pose(
    tiny_scenes,
):
    train, test = tiny_scenes.as_data_source("train"), tiny_scenes.as_data_source("test")
    errors = encoder_pose.train_encoder_on_pose(
        train, test, steps=3, warmup_steps=1, batch_size=4, encoder_channels=(4, 8, 8, 8, 8)
    )
    # The reference, by hand: every test pair scored against the pairs' mean pose.
    examples = [contract.decode_example(test[i]) for i in range(len(test))]
    rotation = np.stack([probes.rotation_vector(e["rotation"]) for e in examples])
    translation = np.stack([e["translation"] / np.linalg.norm(e["translation"]) for e in examples])
    mean_rotation = geometry.rotation_matrix(np.broadcast_to(rotation.mean(0), rotation.shape))
    expected_rotation = geometry.rotation_error_degrees(
        mean_rotation, geometry.rotation_matrix(rotation)
    )
    expected_translation = geometry.translation_error_degrees(
        np.broadcast_to(translation.mean(0), translation.shape), translation
    )
    assert errors["mean_pose"]["rotation_deg"] == pytest.approx(expected_rotation.mean(), rel=1e-4)
    assert errors["mean_pose"]["translation_deg"] == pytest.approx(
        expected_translation.mean(), rel=1e-4
    )
    assert np.isfinite(list(errors["encoder"].values())).all()


# A global-local model whose encoder differs from the probe's defaults in every option
# that could be dropped on the way (strides, kernel size, flow alone, flow scale).
_TRAINED_ENCODER = dict(
    encoder_channels=(4, 8, 8, 8, 8),
    encoder_strides=(2, 2, 2, 1, 1),
    kernel_size=5,
    use_image_pair=False,
    flow_scale=4.0,
)
# Tiny and short: each fit is about a second on CPU.
_PROBE_TRAINING = dict(
    steps=4, warmup_steps=1, batch_size=4, hidden=(16, 16), statistics_batches=2, seed=0
)


@pytest.fixture(scope="module")
def global_local():
    """A GlobalLocal with `_TRAINED_ENCODER` and random (numpy-drawn) variables."""
    model = registry.make_model("global_local", **_TRAINED_ENCODER)
    return model, random_variables(model, 48, 64, seed=1)


@pytest.fixture(scope="module")
def pretrained(global_local):
    return encoder_pose.pretrained_global_encoder(*global_local)


@pytest.fixture(scope="module")
def splits(tiny_scenes):
    return tiny_scenes.as_data_source("train"), tiny_scenes.as_data_source("test")


@pytest.fixture(scope="module")
def pretrained_mlp_fit(splits, pretrained):
    """The MLP on the frozen pretrained encoder."""
    return encoder_pose.fit_pose_probe(
        *splits, train_encoder=False, **pretrained, **_PROBE_TRAINING
    )


@pytest.fixture(scope="module")
def pretrained_full_fit(splits, pretrained):
    """The pretrained encoder trained with the MLP."""
    return encoder_pose.fit_pose_probe(*splits, train_encoder=True, **pretrained, **_PROBE_TRAINING)


@pytest.fixture(scope="module")
def settings(splits, pretrained):
    return encoder_pose.pose_probe_settings(*splits, pretrained=pretrained, **_PROBE_TRAINING)


def _leaves(tree):
    return [np.asarray(leaf) for leaf in jax.tree_util.tree_leaves(tree)]


def _test_poses(test_source):
    """The test pairs' true pose in split order: (ids, rotation vectors, unit translations)."""
    examples = [contract.decode_example(test_source[i]) for i in range(len(test_source))]
    rotation = np.stack([probes.rotation_vector(e["rotation"]) for e in examples])
    translation = np.stack([e["translation"] / np.linalg.norm(e["translation"]) for e in examples])
    return [e["id"] for e in examples], rotation, translation


def test_pretrained_global_encoder_refuses_models_without_a_global_encoder(global_local):
    _, variables = global_local
    for options in (
        dict(use_global_module=False),
        dict(global_source="pose"),
        dict(use_flow=False),
    ):
        with pytest.raises(ValueError, match="global encoder|flow"):
            encoder_pose.pretrained_global_encoder(model_lib.GlobalLocal(**options), variables)
    with pytest.raises(ValueError, match="GlobalLocal"):
        encoder_pose.pretrained_global_encoder(registry.make_model("dispnet"), variables)
    with pytest.raises(ValueError, match="global_encoder"):
        encoder_pose.pretrained_global_encoder(model_lib.GlobalLocal(), {"params": {}})


def test_the_frozen_encoder_is_the_models_and_stays_bit_identical(
    pretrained_mlp_fit, pretrained, global_local, splits
):
    encoder_after = _leaves(pretrained_mlp_fit["params"]["encoder"])
    for after, before in zip(encoder_after, _leaves(pretrained["encoder_params"]), strict=True):
        np.testing.assert_array_equal(after, before)
    # The MLP did train: it starts from PoseMLP's initialisation with the seed's second key.
    head_init = probes.PoseMLP(hidden=(16, 16)).init(
        jax.random.split(jax.random.key(0))[1], np.zeros((1, 6), np.float32)
    )["params"]
    changed = [
        not np.array_equal(after, before)
        for after, before in zip(
            _leaves(pretrained_mlp_fit["params"]["head"]), _leaves(head_init), strict=True
        )
    ]
    assert all(changed)
    # The round trip: the probe's encoder, fed by the probe, gives the model's own g.
    # The standardisation's statistics are those of the model's g over the first two
    # training batches.
    model, variables = global_local

    @jax.jit
    def global_params(batch):
        return layers.apply_model(model, variables, batch)["global_params"]

    keys = ("image1", "image2", "flow")
    batches = iter(
        input_pipeline.train_dataset(
            splits[0], batch_size=4, seed=0, gt_pixels=1, flow_source="gt", keys=keys
        )
    )
    model_global_params = np.concatenate(
        [
            np.asarray(global_params({key: batch[key] for key in keys}), np.float64)
            for batch in itertools.islice(batches, 2)
        ]
    )
    statistics = pretrained_mlp_fit["global_params_statistics"]
    assert model_global_params.shape == (8, 6)
    np.testing.assert_allclose(
        statistics["mean"], model_global_params.mean(0), rtol=1e-4, atol=1e-7
    )
    np.testing.assert_allclose(statistics["std"], model_global_params.std(0), rtol=1e-3)


def test_the_trained_encoder_changes(pretrained_full_fit, pretrained):
    for after, before in zip(
        _leaves(pretrained_full_fit["params"]["encoder"]),
        _leaves(pretrained["encoder_params"]),
        strict=True,
    ):
        assert not np.array_equal(after, before)


def test_encoder_params_must_fit_the_encoder(splits, pretrained):
    with pytest.raises(ValueError, match="do not fit"):
        encoder_pose.fit_pose_probe(
            *splits, **{**pretrained, "encoder_channels": (4, 8, 8, 8, 16)}, **_PROBE_TRAINING
        )


def test_each_setting_predicts_a_rotation_and_a_unit_translation_per_test_pair_in_order(
    settings, splits
):
    ids, _, _ = _test_poses(splits[1])
    assert set(settings["predicted"]) == set(encoder_pose.POSE_PROBE_SETTINGS)
    for poses in settings["predicted"].values():
        assert poses["rotation"].shape == (16, 3, 3) and poses["rotation"].dtype == np.float64
        assert poses["translation"].shape == (16, 3) and poses["translation"].dtype == np.float64
        assert poses["ids"].tolist() == ids
        rotation = poses["rotation"]
        np.testing.assert_allclose(
            rotation @ rotation.transpose(0, 2, 1),
            np.broadcast_to(np.eye(3), rotation.shape),
            atol=1e-9,
        )
        np.testing.assert_allclose(np.linalg.det(rotation), 1.0, atol=1e-9)
        np.testing.assert_allclose(np.linalg.norm(poses["translation"], axis=-1), 1.0, atol=1e-12)


def test_the_settings_errors_are_those_of_their_poses_and_match_single_fits(
    settings, splits, pretrained_mlp_fit, pretrained_full_fit
):
    assert set(settings) == {*encoder_pose.POSE_PROBE_SETTINGS, "mean_pose", "predicted"}
    _, rotation, translation = _test_poses(splits[1])
    truth = np.concatenate([rotation, translation], -1)
    for setting in encoder_pose.POSE_PROBE_SETTINGS:
        poses = settings["predicted"][setting]
        predicted = np.concatenate(
            [probes.rotation_vector(poses["rotation"]), poses["translation"]], -1
        )
        recomputed = probes.pose_errors(predicted, truth)
        for name in ("rotation_deg", "translation_deg"):
            assert settings[setting][name] == pytest.approx(recomputed[name], rel=1e-6)
    mean_pose = probes.pose_errors(np.broadcast_to(truth.mean(0), truth.shape), truth)
    for name in ("rotation_deg", "translation_deg"):
        assert settings["mean_pose"][name] == pytest.approx(mean_pose[name], rel=1e-4)
    # The settings run as single fits with the same options do: same data, seed, steps.
    for setting, fit in (
        ("pretrained_mlp", pretrained_mlp_fit),
        ("pretrained_full", pretrained_full_fit),
    ):
        assert settings[setting] == pytest.approx(fit["probe"], rel=1e-5)
        np.testing.assert_allclose(
            settings["predicted"][setting]["rotation"], fit["predicted"]["rotation"], atol=1e-6
        )
    # Starting from the model's encoder or a random one makes a difference.
    assert not np.allclose(
        settings["predicted"]["scratch_mlp"]["translation"],
        settings["predicted"]["pretrained_mlp"]["translation"],
        atol=1e-3,
    )
