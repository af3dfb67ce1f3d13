"""Tests of gld/analysis/flow_error.py: flow-error normalisation, binned statistics, exclusions,
triangulation with a given pose, the curves over a tiny split, and the figure."""

import math

import numpy as np
import pytest

from gld import input_pipeline
from gld.analysis import flow_error
from gld.models import layers

# ------------------------------------------------------------------ per-pixel errors


def test_flow_error_is_normalised_by_width_and_height():
    height, width = 4, 20
    gt_flow = np.random.default_rng(0).normal(size=(2, height, width, 2)).astype(np.float32)
    shift_u = gt_flow + np.asarray([width / 10, 0.0], np.float32)
    np.testing.assert_allclose(flow_error.normalised_flow_error(shift_u, gt_flow), 0.1, rtol=1e-5)
    # u off by W/10 and v by H/5: sqrt(0.1^2 + 0.2^2), the normalisation of layers.
    shift_uv = gt_flow + np.asarray([width / 10, -height / 5], np.float32)
    np.testing.assert_allclose(
        flow_error.normalised_flow_error(shift_uv, gt_flow), math.sqrt(0.05), rtol=1e-5
    )
    np.testing.assert_allclose(
        flow_error.normalised_flow_error(shift_uv, gt_flow),
        np.linalg.norm(layers.normalise_flow(shift_uv - gt_flow), axis=-1),
        rtol=1e-6,
    )


def test_per_pixel_abs_inv_excludes_and_counts_unusable_predictions():
    depth_true = np.asarray([[2.0, 4.0, 1.0, 1.0, 1.0, 1.0, 0.0, 5.0]], np.float32)
    depth_pred = np.asarray([[1.0, 4.0, 0.0, -1.0, np.nan, np.inf, 1.0, 1.0]], np.float32)
    valid = np.asarray([[True] * 7 + [False]])  # pixel 6: true depth 0; pixel 7: not valid
    error, usable = flow_error.per_pixel_abs_inv(depth_pred, depth_true, valid)
    np.testing.assert_array_equal(usable, [[True, True] + [False] * 6])
    np.testing.assert_allclose(np.asarray(error)[0, :2], [0.5, 0.0])
    assert np.all(np.isnan(np.asarray(error)[0, 2:]))
    # Excluded: valid truth (finite, > 0, in `valid`) with a prediction 0, < 0, NaN, inf.
    truth_valid = valid & (depth_true > 0)
    assert int(np.sum(truth_valid & ~np.asarray(usable))) == 4


# ----------------------------------------------------------------------------- bins


def test_log_edges_cover_every_error_with_four_bins_per_decade():
    edges = flow_error.log_edges()
    assert edges[0] == 0 and edges[-1] == np.inf
    np.testing.assert_allclose(edges[1:-1], 10.0 ** np.arange(-4, 0.01, 0.25))
    assert edges.size - 1 == 18  # underflow, 16 log bins, overflow
    centres = flow_error.bin_centres(edges)
    np.testing.assert_allclose(centres[1], math.sqrt(1e-4 * 10**-3.75))
    np.testing.assert_allclose(centres[0], 10**-4.125)
    np.testing.assert_allclose(centres[-1], 10**0.125)
    with pytest.raises(ValueError, match="from 0 to inf"):
        flow_error.bin_statistics(np.zeros(1), np.zeros(1), np.ones(1, bool), [0.0, 1.0])


def test_binning_known_values_and_merging_halves():
    edges = [0.0, 1.0, 10.0, np.inf]
    flow_errors = np.asarray([0.5, 0.2, 1.0, 5.0, 9.0, 20.0, 3.0, 0.1])
    depth_errors = np.asarray([1.0, 3.0, 2.0, 4.0, 6.0, 7.0, 100.0, np.nan])
    mask = np.asarray([True] * 6 + [False, False])  # the masked-out values are ignored
    bins = flow_error.bin_statistics(flow_errors, depth_errors, mask, edges)
    summary = flow_error.summarise(bins)
    # Bin [0, 1): 1, 3; bin [1, 10): 2, 4, 6 (1.0 sits on an edge: the bin it opens);
    # bin [10, inf): 7.
    np.testing.assert_array_equal(summary["count"], [2, 3, 1])
    np.testing.assert_allclose(summary["mean"], [2.0, 4.0, 7.0])
    np.testing.assert_allclose(summary["std"], [1.0, math.sqrt(8 / 3), 0.0])
    np.testing.assert_array_equal(summary["edges"], edges)

    first = flow_error.bin_statistics(flow_errors[:3], depth_errors[:3], mask[:3], edges)
    second = flow_error.bin_statistics(flow_errors[3:], depth_errors[3:], mask[3:], edges)
    merged = first + second
    for field in ("sum", "sum_squares", "count"):
        np.testing.assert_allclose(getattr(merged, field), getattr(bins, field))
    with pytest.raises(ValueError, match="different edges"):
        merged.add(flow_error.FlowErrorBins.zeros([0.0, 2.0, np.inf]))


def test_empty_bins_have_nan_mean_and_zero_count():
    edges = [0.0, 1.0, 10.0, np.inf]
    bins = flow_error.bin_statistics(np.asarray([0.5]), np.asarray([2.0]), np.ones(1, bool), edges)
    summary = flow_error.summarise(bins)
    np.testing.assert_array_equal(summary["count"], [1, 0, 0])
    assert summary["mean"][0] == 2.0 and np.all(np.isnan(summary["mean"][1:]))
    assert np.all(np.isnan(summary["std"][1:]))
    empty = flow_error.summarise(flow_error.FlowErrorBins.zeros(edges))
    assert np.all(empty["count"] == 0) and np.all(np.isnan(empty["mean"]))


# ------------------------------------------------------- triangulation on tiny scenes


def test_triangulating_true_flow_with_true_pose_recovers_depth(eval_batch):
    batch = dict(eval_batch, flow=eval_batch["gt_flow"])
    checked = eval_batch["gt_flow_valid"] & eval_batch["depth_valid"]
    assert checked.sum() > 1000

    def relative_error(rotation, translation):
        depth = flow_error.triangulated_depth(batch, rotation, translation)
        assert depth.shape == eval_batch["depth"].shape
        truth = eval_batch["depth"]
        return np.abs(depth - truth)[checked] / truth[checked]

    true_pose = relative_error(eval_batch["rotation"], eval_batch["translation"])
    assert np.median(true_pose) < 1e-3 and np.mean(true_pose < 0.01) > 0.95
    # A predicted unit direction is at the batch's scale: any norm gives the same depth.
    np.testing.assert_allclose(
        relative_error(eval_batch["rotation"], 3.0 * eval_batch["translation"]), true_pose
    )
    wrong_pose = relative_error(eval_batch["rotation"], np.roll(eval_batch["translation"], 1, -1))
    assert np.median(wrong_pose) > 0.1


# ----------------------------------------------------------------------------- curves


def test_true_depth_gives_zero_error_and_counts_every_usable_pixel(tiny_scenes):
    source = tiny_scenes.as_data_source("test")
    seen_keys = []

    def true_depth(batch):
        seen_keys.append(set(batch))
        return batch["depth"]

    curves = flow_error.flow_error_curves(
        {
            "truth": flow_error.DepthMethod(true_depth),
            "triangulation_gt_pose": flow_error.triangulation_predictor(),
        },
        source,
        batch_size=3,
        max_examples=4,  # 2 batches, the second with 2 padded rows
    )
    # The pipeline decoded what the analysis and the triangulation read, no images.
    assert seen_keys[0] == {
        *flow_error.ANALYSIS_KEYS,
        *flow_error.TRIANGULATION_KEYS,
        *flow_error.POSE_KEYS,
        "id",
        "example_mask",
    }
    first_four = next(
        input_pipeline.eval_batches(source, batch_size=4, keys=("gt_flow_valid", "depth_valid"))
    )
    expected_pixels = int(np.sum(first_four["gt_flow_valid"] & first_four["depth_valid"]))
    truth = curves["truth"]
    assert expected_pixels > 1000
    assert truth["pixels"] == int(truth["count"].sum()) == expected_pixels
    assert truth["excluded_pixels"] == 0
    filled = truth["count"] > 0
    assert filled.sum() >= 3  # the estimated flow's errors spread over several bins
    np.testing.assert_array_equal(truth["mean"][filled], 0.0)
    np.testing.assert_array_equal(truth["std"][filled], 0.0)
    assert np.all(np.isnan(truth["mean"][~filled]))

    triangulation = curves["triangulation_gt_pose"]
    assert triangulation["pixels"] == expected_pixels  # its fallback fills every pixel
    assert np.nanmax(triangulation["mean"]) > 0


def test_predictor_exclusions_are_counted(tiny_scenes):
    def half_invalid(batch):
        depth = np.array(batch["depth"])
        depth[..., ::2] = np.nan
        return depth

    source = tiny_scenes.as_data_source("test")
    curves = flow_error.flow_error_curves(
        {"half": half_invalid}, source, batch_size=2, max_examples=2
    )
    first_two = next(
        input_pipeline.eval_batches(source, batch_size=2, keys=("gt_flow_valid", "depth_valid"))
    )
    counted = first_two["gt_flow_valid"] & first_two["depth_valid"]
    assert curves["half"]["excluded_pixels"] == int(counted[..., ::2].sum()) > 0
    assert curves["half"]["pixels"] == int(counted[..., 1::2].sum()) > 0


def test_true_flow_is_refused():
    with pytest.raises(ValueError, match="error is 0 everywhere"):
        flow_error.flow_error_curves({"x": lambda batch: None}, [], batch_size=1, flow_source="gt")


def test_curves_are_drawn(tmp_path):
    edges = flow_error.log_edges()
    rng = np.random.default_rng(0)
    errors = 10 ** rng.uniform(-4.5, 0.5, 500)
    curves = {
        name: flow_error.summarise(
            flow_error.bin_statistics(errors, slope * errors, np.ones(500, bool), edges)
        )
        for name, slope in (("global_local", 0.1), ("triangulation_gt_pose", 1.0))
    }
    path = flow_error.draw_flow_error_curves(curves, tmp_path / "figs" / "flow_errors.png")
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert path.stat().st_size > 5000


def test_model_predictor_reads_the_model_inputs_only():
    from conftest import TINY_MODEL, random_variables

    from gld.models.global_local import GlobalLocal

    model = GlobalLocal(**TINY_MODEL)
    predictor = flow_error.model_predictor(model, random_variables(model, 48, 64, seed=0))
    assert predictor.keys == ("image1", "image2", "flow")
    rng = np.random.default_rng(0)
    batch = {
        "image1": rng.uniform(-0.5, 0.5, (2, 48, 64, 3)).astype(np.float32),
        "image2": rng.uniform(-0.5, 0.5, (2, 48, 64, 3)).astype(np.float32),
        "flow": rng.normal(size=(2, 48, 64, 2)).astype(np.float32),
    }
    depth = np.asarray(predictor(batch))
    assert depth.shape == (2, 48, 64) and np.all(np.isfinite(depth) & (depth > 0))
