"""Metric scale recovery (gld/inference/scale.py): from the baseline and from range readings."""

import numpy as np
import pytest

from gld import contract, records
from gld.inference import metric_scale, scale


def _depth_map(height=12, width=16):
    """A smooth positive map with a distinct value at every pixel (a tilted plane)."""
    v, u = np.mgrid[0:height, 0:width].astype(np.float64)
    return (1.0 + 0.1 * u + 0.05 * v).astype(np.float32)


def test_scale_from_baseline_is_the_baseline_and_refuses_zero():
    np.testing.assert_allclose(metric_scale.scale_from_baseline(0.25), 0.25)
    np.testing.assert_allclose(metric_scale.scale_from_baseline([0.1, 2.0]), [0.1, 2.0])
    assert metric_scale.scale_from_baseline(0.25).dtype == np.float32
    with pytest.raises(ValueError, match="baseline.*got 0.0"):
        metric_scale.scale_from_baseline(0.0)
    with pytest.raises(ValueError, match="at index 1"):
        metric_scale.scale_from_baseline([0.3, np.nan])


def test_scale_from_ranges_is_exact_for_a_noiseless_map():
    depth = _depth_map()
    true_scale = 2.7
    # Sub-pixel readings: the plane is linear in (u, v), so bilinear lookup is exact.
    pixels = np.array([[0.0, 0.0], [3.25, 7.5], [15.0, 11.0], [8.6, 2.1]])
    distances = true_scale * (1.0 + 0.1 * pixels[:, 0] + 0.05 * pixels[:, 1])
    np.testing.assert_allclose(
        metric_scale.scale_from_ranges(depth, pixels, distances), true_scale, 1e-6
    )
    # One reading is enough, and so is one reading at the image's very edge.
    np.testing.assert_allclose(
        metric_scale.scale_from_ranges(depth, pixels[1:2], distances[1:2]), true_scale, 1e-6
    )
    np.testing.assert_allclose(
        metric_scale.scale_from_ranges(depth, [[15.5, 11.5]], [true_scale * depth[11, 15]]),
        true_scale,
        1e-6,
    )


def test_scale_from_ranges_with_noise_stays_within_bound_and_ignores_outliers():
    rng = np.random.default_rng(0)
    depth = _depth_map(48, 64)
    true_scale = 0.8
    count = 201
    pixels = np.stack([rng.uniform(0, 63, count), rng.uniform(0, 47, count)], -1)
    truth = true_scale * (1.0 + 0.1 * pixels[:, 0] + 0.05 * pixels[:, 1])
    # 2% multiplicative noise: the median of 201 ratios is within 0.5% of the truth
    # (its standard error is ~0.2%).
    noisy = truth * (1.0 + 0.02 * rng.standard_normal(count))
    assert abs(metric_scale.scale_from_ranges(depth, pixels, noisy) / true_scale - 1.0) < 0.005
    # A fifth of the readings wild (10x too far) moves the median to the inliers' 62.5th
    # percentile, ~0.3 noise sigma = 0.6% here: bound 1.5%.
    noisy[: count // 5] *= 10.0
    assert abs(metric_scale.scale_from_ranges(depth, pixels, noisy) / true_scale - 1.0) < 0.015
    # The mean ratio would be ruined by them.
    assert np.mean(noisy / (truth / true_scale)) > 2.0 * true_scale


def test_scale_from_ranges_batched_matches_one_by_one():
    depth = np.stack([_depth_map(), 3.0 * _depth_map()])
    pixels = np.array([[[1.0, 2.0], [5.0, 5.0]], [[0.0, 0.0], [9.5, 3.5]]])
    distances = np.array([[4.0, 5.0], [2.0, 3.0]])
    batched = metric_scale.scale_from_ranges(depth, pixels, distances)
    assert batched.shape == (2,)
    for index in range(2):
        np.testing.assert_allclose(
            batched[index],
            metric_scale.scale_from_ranges(depth[index], pixels[index], distances[index]),
        )


@pytest.mark.parametrize(
    "pixels, distances, message",
    [
        ([[16.0, 3.0]], [1.0], r"reading 0 \(u=16.0, v=3.0.*outside the 16x12 image"),
        ([[2.0, 3.0], [1.0, -0.6]], [1.0, 1.0], "reading 1.*outside"),
        ([[2.0, 3.0]], [0.0], "reading 0.*distance must be > 0"),
        ([[2.0, 3.0]], [-1.0], "distance must be > 0"),
        ([[2.0, np.nan]], [1.0], "reading 0.*not finite"),
        ([[2.0, 3.0]], [np.inf], "not finite"),
        ([[2.0, 3.0]], [1.0, 2.0], "distances must be"),
        (np.zeros((0, 2)), np.zeros(0), "N >= 1"),
    ],
)
def test_scale_from_ranges_names_the_bad_reading(pixels, distances, message):
    with pytest.raises(ValueError, match=message):
        metric_scale.scale_from_ranges(_depth_map(), pixels, distances)


def test_scale_from_ranges_refuses_a_reading_where_depth_is_not_positive():
    depth = _depth_map()
    depth[4, 5] = np.nan
    with pytest.raises(ValueError, match=r"reading 0 \(u=5.0, v=4.0\).*not a positive depth"):
        metric_scale.scale_from_ranges(depth, [[5.0, 4.0]], [1.0])


def _stored_pair(rng, index, baseline):
    """A stored record (`gld.records`) of a pair with the given baseline, in metres."""
    depth = rng.uniform(1.0, 4.0, (6, 8)).astype(np.float32)
    direction = rng.standard_normal(3)
    intrinsics = np.array([1.0, 1.0, 0.5, 0.5], np.float32)
    return records.encode(
        {
            "image1": rng.integers(0, 256, (6, 8, 3), dtype=np.uint8),
            "image2": rng.integers(0, 256, (6, 8, 3), dtype=np.uint8),
            "depth1": depth,
            "depth2": depth,
            "intrinsics1": intrinsics,
            "intrinsics2": intrinsics,
            "rotation": np.eye(3, dtype=np.float32),
            "translation": (baseline * direction / np.linalg.norm(direction)).astype(np.float32),
            "flow": np.zeros((6, 8, 2), np.float32),
            "gt_flow": np.zeros((6, 8, 2), np.float32),
            "gt_flow_valid": np.ones((6, 8), bool),
            "id": f"pair{index}",
        }
    )


def test_measure_scale_recovery_scores_each_scale_against_the_metric_truth():
    """A perfect predictor (metric depth / ||t||): the true baseline, one reading and the
    per-pair median recover the metric truth exactly; the training mean baseline is off
    by |mean / ||t|| - 1| per pair."""
    rng = np.random.default_rng(1)
    baselines = [0.1, 0.5, 0.3]
    test_records = [_stored_pair(rng, i, b) for i, b in enumerate(baselines)]
    perfect = [
        example["depth"] / np.linalg.norm(example["translation"])
        for example in map(contract.decode_example, test_records)
    ]
    done = []

    def predict_depth(image1, image2, flow):
        start = len(done)
        done.extend(range(len(image1)))
        return np.stack(perfect[start : start + len(image1)])

    train_records = [_stored_pair(rng, 10 + i, b) for i, b in enumerate([0.1, 0.3])]
    result = scale.measure_scale_recovery(predict_depth, test_records, train_records, batch_size=2)
    methods = result["methods"]
    assert result["num_examples"] == 3 and len(done) == 3
    np.testing.assert_allclose(result["train_mean_baseline"], 0.2, rtol=1e-6)
    assert methods["true_baseline"]["abs_rel"] < 1e-6
    assert methods["one_reading"]["abs_rel"] < 1e-5
    assert methods["oracle_best_scale"]["abs_rel"] < 1e-6
    expected = np.mean([abs(0.2 / b - 1.0) for b in baselines])
    np.testing.assert_allclose(methods["train_mean_baseline"]["abs_rel"], expected, rtol=1e-5)
    assert "training-set mean baseline" in scale.scale_table(result)


def test_best_abs_rel_scale_beats_every_other_scale():
    rng = np.random.default_rng(3)
    depth = rng.uniform(0.5, 2.0, (8, 10))
    truth = 1.7 * depth * rng.lognormal(0.0, 0.3, depth.shape)
    truth[0, :3] = 0.0  # invalid truth is ignored
    best = scale.best_abs_rel_scale(depth, truth)
    error = scale.abs_rel(best * depth, truth)
    grid = np.linspace(0.5, 4.0, 2001)
    assert error <= min(scale.abs_rel(s * depth, truth) for s in grid) + 1e-9
    # The plain median of truth / depth is not the minimiser in general.
    valid = truth > 0
    assert error < scale.abs_rel(np.median(truth[valid] / depth[valid]) * depth, truth)


def test_ray_length_becomes_camera_z():
    camera = np.array([[100.0, 0, 40.0], [0, 120.0, 30.0], [0, 0, 1]])
    point = np.array([0.6, -0.2, 3.0])
    pixel = (camera @ point)[:2] / point[2]
    depth = metric_scale.ray_length_to_depth([pixel], [np.linalg.norm(point)], camera)
    np.testing.assert_allclose(depth, [3.0], rtol=1e-12)
    # At the principal point the ray is the optical axis.
    np.testing.assert_allclose(
        metric_scale.ray_length_to_depth([[40.0, 30.0]], [2.0], camera), [2.0]
    )
