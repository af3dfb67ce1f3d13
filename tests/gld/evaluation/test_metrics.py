import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from gld.evaluation import metrics


def test_depth_metrics_by_hand():
    truth = jnp.array([[[1.0, 2.0], [4.0, 0.0]]])
    prediction = jnp.array([[[2.0, 2.0], [2.0, 7.0]]])
    valid = truth > 0
    result = jax.jit(metrics.depth_metrics)(prediction, truth, valid)
    assert float(result["abs_inv"][0]) == pytest.approx((0.5 + 0 + 0.25) / 3)
    assert float(result["abs_rel"][0]) == pytest.approx((1.0 + 0 + 0.5) / 3)
    log_errors = np.log([1 / 2, 1.0, 2.0])
    expected = math.sqrt(np.mean(log_errors**2) - np.mean(log_errors) ** 2)
    assert float(result["s_rmse"][0]) == pytest.approx(expected, rel=1e-5)
    assert float(result["num_pixels"][0]) == 3


def test_non_finite_and_non_positive_predictions_are_excluded_and_counted():
    truth = jnp.array([[[2.0, 2.0], [2.0, 2.0]], [[1.0, 0.0], [4.0, 4.0]]])
    nan, inf = float("nan"), float("inf")
    # Example 0: two of four predictions are not positive. Example 1: NaN and inf on
    # valid truth, NaN on the invalid truth pixel (not counted: no truth to score).
    prediction = jnp.array([[[2.0, 4.0], [0.0, -1.0]], [[nan, nan], [inf, 2.0]]])
    result = jax.jit(metrics.depth_metrics)(prediction, truth, truth > 0)
    np.testing.assert_array_equal(result["num_pixels"], [2, 1])
    np.testing.assert_array_equal(result["excluded_pixels"], [2, 2])
    # Example 0 scores (2 vs 2) and (2 vs 4); example 1 scores (4 vs 2).
    np.testing.assert_allclose(result["abs_inv"], [(0 + 0.25) / 2, 0.25], rtol=1e-6)
    np.testing.assert_allclose(result["abs_rel"], [(0 + 1.0) / 2, 0.5], rtol=1e-6)
    # E = [0, -ln 2]: mean(E^2) - mean(E)^2 = (ln 2)^2 / 4; one pixel has no spread.
    np.testing.assert_allclose(result["s_rmse"], [math.log(2) / 2, 0.0], rtol=1e-5, atol=1e-7)


def _depth_metrics_before_masking(depth_pred, depth_true, valid):
    """gld's depth_metrics before predictions were masked (the seeded runs' numbers)."""
    valid = valid & (depth_true > 0) & jnp.isfinite(depth_true)
    safe_true = jnp.where(valid, depth_true, 1.0)
    safe_pred = jnp.where(valid, jnp.maximum(depth_pred, 1e-12), 1.0)
    weight = valid.astype(jnp.float32)
    count = jnp.sum(weight, axis=(1, 2))
    denominator = jnp.maximum(count, 1.0)

    def mean(values):
        return jnp.sum(values * weight, axis=(1, 2)) / denominator

    log_error = jnp.log(safe_true) - jnp.log(safe_pred)
    variance = mean(log_error**2) - mean(log_error) ** 2
    return {
        "abs_inv": mean(jnp.abs(1.0 / safe_true - 1.0 / safe_pred)),
        "abs_rel": mean(jnp.abs(safe_true - safe_pred) / safe_true),
        "s_rmse": jnp.sqrt(jnp.maximum(variance, 0.0)),
        "num_pixels": count,
    }


def test_positive_finite_predictions_score_exactly_as_before_masking():
    rng = np.random.default_rng(3)
    truth = rng.uniform(0.5, 20.0, (4, 24, 32)).astype(np.float32)
    truth[rng.random(truth.shape) < 0.2] = 0.0  # invalid ground truth
    truth[0, 0, :3] = [np.nan, np.inf, -1.0]
    # Positive predictions over six decades, as the global-local model's can be.
    prediction = (10.0 ** rng.uniform(-3, 3, truth.shape)).astype(np.float32)
    valid = np.isfinite(truth) & (truth > 0)
    # Compiled (as `gld.evaluation.evaluate` runs them) and op by op, each against its like.
    for wrap in (jax.jit, lambda function: function):
        before = wrap(_depth_metrics_before_masking)(prediction, truth, valid)
        now = wrap(metrics.depth_metrics)(prediction, truth, valid)
        for name, values in before.items():
            np.testing.assert_array_equal(np.asarray(now[name]), np.asarray(values), name)
        np.testing.assert_array_equal(now["excluded_pixels"], 0)
    # The old formula scored 25 non-positive pixels as 1e-12 depth: Abs-Inv ~1e9.
    prediction[1, :5, :5] = 0.0
    before = _depth_metrics_before_masking(prediction, truth, valid)
    now = metrics.depth_metrics(prediction, truth, valid)
    assert float(before["abs_inv"][1]) > 1e8
    assert float(now["abs_inv"][1]) < 10 * float(now["abs_inv"][0])
    assert float(now["excluded_pixels"][1]) == valid[1, :5, :5].sum()


def test_an_example_without_a_scored_pixel_is_left_out_of_the_means_and_counted():
    truth = jnp.full((2, 2, 2), 2.0)
    prediction = jnp.stack([jnp.full((2, 2), 4.0), jnp.zeros((2, 2))])
    per_example = {
        k: np.asarray(v) for k, v in metrics.depth_metrics(prediction, truth, truth > 0).items()
    }
    assert np.isnan(per_example["abs_inv"][1]) and per_example["excluded_pixels"][1] == 4
    summary = metrics.summarise(per_example, np.array([True, True]))
    assert summary["abs_inv"] == {"mean": 0.25, "std": 0.0, "count": 1}
    assert summary["excluded_pixels"] == {"mean": 2.0, "std": 2.0, "count": 2}
    assert metrics.excluded_pixels(summary) == {
        "pixels": 4,
        "valid_pixels": 8,
        "fraction": 0.5,
        "per_example": 2.0,
        "unscored_examples": 1,
    }


def test_resize_nearest_takes_the_pixel_under_each_centre():
    depth = np.arange(10, dtype=np.float32).reshape(2, 5)
    # Rows 2 -> 4: centres at 0.25, 0.75, 1.25, 1.75 source rows. Columns 5 -> 2: centres
    # at 1.25 and 3.75 source columns.
    np.testing.assert_array_equal(
        metrics.resize_nearest(depth, 4, 2), [[1, 3], [1, 3], [6, 8], [6, 8]]
    )
    # Columns 2 -> 5: centres at 0.2, 0.6, 1.0 (the border: the later pixel), 1.4, 1.8.
    row = np.array([[7.0, 9.0]])
    np.testing.assert_array_equal(metrics.resize_nearest(row, 1, 5), [[7, 7, 9, 9, 9]])
    batched = jax.jit(metrics.resize_nearest, static_argnums=(1, 2))(jnp.stack([depth] * 3), 4, 2)
    np.testing.assert_array_equal(batched[2], metrics.resize_nearest(depth, 4, 2))


def test_scale_invariant_rmse_ignores_a_global_scale_but_others_do_not():
    truth = jnp.asarray(np.random.default_rng(0).uniform(1, 5, (1, 4, 4)), jnp.float32)
    valid = jnp.ones_like(truth, bool)
    result = metrics.depth_metrics(truth * 3.0, truth, valid)
    assert float(result["s_rmse"][0]) == pytest.approx(0.0, abs=1e-3)
    assert float(result["abs_rel"][0]) == pytest.approx(2.0, rel=1e-5)


def test_examples_without_valid_pixels_are_marked_and_summary_ignores_padding():
    truth = jnp.zeros((1, 2, 2))
    result = metrics.depth_metrics(jnp.ones((1, 2, 2)), truth, truth > 0)
    assert float(result["num_pixels"][0]) == 0
    summary = metrics.summarise(
        {"abs_inv": np.array([1.0, 3.0, 100.0])}, np.array([True, True, False])
    )
    assert summary["abs_inv"] == {"mean": 2.0, "std": 1.0, "count": 2}


def test_pose_errors():
    rotation = np.eye(3)[None]
    errors = metrics.pose_errors(
        rotation, np.array([[0, 0, 1.0]]), rotation, np.array([[0, 1, 0.0]])
    )
    assert float(errors["rotation_deg"][0]) == pytest.approx(0.0, abs=1e-5)
    assert float(errors["translation_deg"][0]) == pytest.approx(90.0)


def test_table_carries_the_protocol_stamp():
    summary = {name: {"mean": 0.5, "std": 0.1, "count": 2} for name in metrics.DEPTH_METRICS}
    stamp = metrics.protocol_stamp(192, 256, 2)
    table = metrics.markdown_table([("global_local", summary)], stamp)
    assert "| global_local | 0.5000 ± 0.1000 |" in table
    assert "256x192" in table and "||t|| = 1" in table and "no median scaling" in table
    assert "ground truth at the records' resolution, 256x192 px" in stamp
    assert "whose prediction is finite and positive" in stamp
    # Summaries without pixel counts get no exclusion line.
    assert "Excluded" not in table


def test_the_stamp_says_where_the_truth_was_scored():
    stamp = metrics.protocol_stamp(
        192, 256, 80, truth_resolution="file", file_resolutions={"640x480": 79, "320x240": 1}
    )
    assert stamp.startswith(
        "protocol: ground truth at the source files' resolution (79 at 640x480, 1 at "
        "320x240), read from the files by example id, each prediction resized to it by "
        "centre-aligned nearest neighbour as DeMoN's evaluation does (records at 256x192 px); "
        "depth scaled so that ||t|| = 1;"
    )
    assert "records' resolution" not in stamp
    assert "DeMoN evaluates at the file's, truth_resolution=file" in metrics.protocol_stamp(
        192, 256, 80
    )
    with pytest.raises(ValueError, match="unknown truth_resolution 'native'"):
        metrics.protocol_stamp(192, 256, 80, truth_resolution="native")


def test_truth_resolutions_are_counted_as_width_by_height_most_frequent_first():
    shapes = [(240, 320), (480, 640), (480, 640), (192, 256), (480, 640)]
    counts = metrics.resolution_counts(shapes)
    assert counts == {"640x480": 3, "320x240": 1, "256x192": 1}
    assert list(counts)[0] == "640x480"
    assert metrics.resolution_counts([]) == {}


def test_the_records_protocol_is_named_with_its_order():
    demon = {"image_decoder": "demon", "depth_resampling": "demon", "order": "demon"}
    assert metrics.records_protocol_note(demon) == (
        "records built with image_decoder=demon, depth_resampling=demon; evaluated in the "
        "records' stored order, order=demon (DeMoN's reader's: files as listed, each file's "
        "scene groups reverse-sorted)"
    )
    assert metrics.records_protocol_note({"image_decoder": "opencv"}) == (
        "records built with image_decoder=opencv; evaluated in the records' stored order"
    )


def test_table_says_how_many_pixels_each_method_had_excluded():
    def summary(excluded_mean, scored_mean, scored_examples):
        values = {
            name: {"mean": 0.5, "std": 0.1, "count": scored_examples}
            for name in metrics.DEPTH_METRICS
        }
        values["num_pixels"] = {"mean": scored_mean, "std": 0.0, "count": 4}
        values["excluded_pixels"] = {"mean": excluded_mean, "std": 0.0, "count": 4}
        return values

    rows = [("other", summary(6.25, 1000.0, 3)), ("dataset_mean", summary(0.0, 1006.25, 4))]
    table = metrics.markdown_table(rows, "stamp")
    note = (
        "Excluded pixels (valid ground truth, prediction not finite or not positive): "
        "other 25 of 4,025 (0.62%), 1 example(s) without a scored pixel left out of its means."
    )
    assert table.splitlines()[-3] == note
    assert table.endswith(f"{note}\n\nstamp\n")
    clean = metrics.markdown_table(rows[1:], "stamp")
    assert (
        "Excluded pixels (valid ground truth, prediction not finite or not positive): none."
        in clean
    )


def _summary(abs_inv: float) -> dict[str, dict]:
    return {
        name: {"mean": abs_inv if name == "abs_inv" else 0.5, "std": 0.1, "count": 2}
        for name in metrics.DEPTH_METRICS
    }


def test_table_gives_abs_inv_as_a_multiple_of_the_dataset_mean():
    rows = [
        ("global_local", _summary(0.03)),
        ("dataset_mean", _summary(0.04)),
        ("oracle_pair_median", _summary(0.01)),
    ]
    assert metrics.ratios_to_reference(rows) == pytest.approx(
        {"global_local": 0.75, "dataset_mean": 1.0, "oracle_pair_median": 0.25}
    )
    table = metrics.markdown_table(
        rows, "stamp", labels={"oracle_pair_median": "per-pair oracle constant"}
    )
    lines = table.splitlines()
    assert lines[0] == "| method | Abs-Inv | Abs-Rel | S-RMSE | Abs-Inv ÷ dataset_mean |"
    assert lines[1] == "|---|---|---|---|---|"
    assert lines[2].startswith("| global_local | 0.0300 ± 0.1000 |")
    assert lines[2].endswith("| 0.75× |")
    assert lines[3].endswith("| 1.00× |")
    assert lines[4].startswith("| oracle_pair_median — per-pair oracle constant | 0.0100")
    assert lines[4].endswith("| 0.25× |")


def test_table_without_the_reference_has_no_ratio_column():
    assert metrics.ratios_to_reference([("global_local", _summary(0.03))]) == {}
    assert metrics.ratios_to_reference([("dataset_mean", _summary(0.0))]) == {}
    table = metrics.markdown_table([("global_local", _summary(0.03))], "stamp")
    assert table.splitlines()[0] == "| method | Abs-Inv | Abs-Rel | S-RMSE |"
