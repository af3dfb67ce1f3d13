"""Tests of gld/probes.py: pair statistics, rotation vectors, the pose probe, collect."""

import numpy as np
import pytest

from gld import geometry, input_pipeline, probes
from gld import model as model_lib


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
    translations = [input_pipeline.decode_example(source[i])["translation"] for i in range(7)]
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
    errors = probes.train_encoder_on_pose(
        train, test, steps=3, warmup_steps=1, batch_size=4, encoder_channels=(4, 8, 8, 8, 8)
    )
    # The reference, by hand: every test pair scored against the pairs' mean pose.
    examples = [input_pipeline.decode_example(test[i]) for i in range(len(test))]
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
