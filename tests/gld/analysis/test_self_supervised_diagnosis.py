import numpy as np
import pytest

from gld.analysis import self_supervised_diagnosis as diagnosis
from gld.models.baselines.self_supervised import SelfSupervised
from tests.conftest import random_variables


def _truth(depth, valid=None):
    depth = np.asarray(depth, np.float64)
    return {"depth": depth, "depth_valid": np.ones(depth.shape, bool) if valid is None else valid}


def test_median_scaling_removes_the_scale_and_keeps_the_shape():
    rng = np.random.default_rng(0)
    truth = rng.uniform(1.0, 10.0, (2, 6, 8))
    batch = _truth(truth)
    np.testing.assert_allclose(
        diagnosis.median_scaled(truth * [[[3.0]], [[0.2]]], batch), truth, rtol=1e-5
    )
    # A flat map lands on the truth's median inverse depth (the oracle constant).
    flat = diagnosis.median_scaled(np.full_like(truth, 7.0), batch)
    np.testing.assert_allclose(1 / flat[0], np.median(1 / truth[0]), rtol=1e-5)


def test_median_scaling_reads_only_valid_truth_pixels():
    truth = np.full((1, 4, 4), 2.0)
    valid = np.zeros((1, 4, 4), bool)
    valid[0, :2] = True
    truth[0, 2:] = 1000.0  # invalid: must not move the median
    predicted = np.full((1, 4, 4), 5.0)
    predicted[0, 2:] = 0.01
    scaled = diagnosis.median_scaled(predicted, _truth(truth, valid))
    np.testing.assert_allclose(scaled[0, :2], 2.0, rtol=1e-5)


def test_pose_errors_in_degrees():
    angle = np.radians(10.0)
    rotation = np.array(
        [[np.cos(angle), -np.sin(angle), 0], [np.sin(angle), np.cos(angle), 0], [0, 0, 1]]
    )
    batch = {"rotation": rotation[None], "translation": np.array([[1.0, 0, 0]])}
    outputs = {"rotation": np.eye(3)[None], "translation": np.array([[0.0, 2.0, 0]])}
    errors = diagnosis.pose_errors(outputs, batch)
    np.testing.assert_allclose(errors["rotation_deg"], [10.0], atol=1e-6)
    np.testing.assert_allclose(errors["identity_rotation_deg"], [10.0], atol=1e-6)
    np.testing.assert_allclose(errors["translation_deg"], [90.0], atol=1e-6)


@pytest.fixture(scope="module")
def tiny_test_batches(tiny_scenes):
    from gld.evaluation import evaluate as evaluation

    source = tiny_scenes.as_data_source("test")
    # Batches of 6 over 16 pairs: the last one is padded.
    return list(
        evaluation.split_batches(
            source,
            batch_size=6,
            flow_source="estimated",
            max_examples=0,
            progress=False,
            all_processes=False,
        )
    )


def test_the_photometric_loss_is_lowest_at_the_truth(tiny_test_batches):
    at_truth = diagnosis.photometric_at_truth(tiny_test_batches)
    assert set(at_truth) == set(diagnosis.SPOILED_TRUTH)
    truth = at_truth[diagnosis.TRUTH]["photometric"]
    for name, terms in at_truth.items():
        if name != diagnosis.TRUTH:
            assert terms["photometric"] > truth, name
    # Padded rows are left out: the padded batches give the unpadded pairs' loss.
    whole = [{k: v[b["example_mask"]] for k, v in b.items()} for b in tiny_test_batches]
    again = diagnosis.photometric_at_truth(whole)
    assert again[diagnosis.TRUTH]["photometric"] == pytest.approx(truth, rel=1e-5)


def test_diagnose_model_scores_as_the_evaluation_does(tiny_scenes, tiny_test_batches):
    import jax

    from gld.evaluation import evaluate as evaluation
    from gld.models import layers

    model = SelfSupervised(num_scales=1)
    variables = random_variables(model, 48, 64, seed=0)
    per_pair = diagnosis.diagnose_model(model, variables, tiny_test_batches)
    assert {len(v) for v in per_pair.values()} == {16}  # the real pairs only
    apply = jax.jit(lambda b: layers.apply_model(model, variables, b, train=False)["depth"])

    def predict(batch, scaled):
        depth = np.asarray(apply({k: batch[k] for k in layers.input_keys(model)}))
        return {"depth": diagnosis.median_scaled(depth, batch) if scaled else depth}

    source = tiny_scenes.as_data_source("test")
    for suffix, scaled in (("", False), ("_median_scaled", True)):
        scored, _ = evaluation.evaluate_predictor(lambda b, s=scaled: predict(b, s), source)
        mask = scored["example_mask"]
        np.testing.assert_allclose(per_pair["abs_inv" + suffix], scored["abs_inv"][mask], rtol=1e-4)
    assert np.all((per_pair["translation_deg"] >= 0) & (per_pair["translation_deg"] <= 180))
