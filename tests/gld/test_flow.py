"""Tests of gld/flow.py: estimators on a known translation, input forms, exact flow, EPE."""

import numpy as np
import pytest

from gld import flow

HEIGHT, WIDTH = 48, 64
# I2 is I1 moved 3 px right and 2 px up: pixel p of I1 sits at p + (3, -2) in I2.
SHIFT = np.array([3.0, -2.0])


def _texture(shift=(0.0, 0.0)) -> np.ndarray:
    """[H, W, 3] uint8 grey texture of smooth random waves, moved by `shift` (x, y) px."""
    y, x = np.mgrid[0:HEIGHT, 0:WIDTH].astype(np.float64)
    x, y = x - shift[0], y - shift[1]
    rng = np.random.default_rng(0)
    value = np.zeros((HEIGHT, WIDTH))
    for _ in range(12):
        frequency = rng.uniform(0.1, 0.5, 2) * rng.choice([-1, 1], 2)
        value += np.sin(frequency[0] * x + frequency[1] * y + rng.uniform(0, 2 * np.pi))
    value = (value - value.min()) / (value.max() - value.min())
    return np.repeat(np.rint(value * 255).astype(np.uint8)[..., None], 3, axis=-1)


@pytest.fixture(scope="module")
def pair():
    return _texture(), _texture(SHIFT)


@pytest.mark.parametrize("method", sorted(flow.ESTIMATORS))
def test_every_estimator_recovers_a_known_translation(pair, method):
    estimate = flow.estimate(*pair, method=method)
    assert estimate.shape == (HEIGHT, WIDTH, 2) and estimate.dtype == np.float32
    inner = estimate[8:-8, 8:-8].reshape(-1, 2)  # away from the border the shift uncovers
    np.testing.assert_allclose(np.median(inner, axis=0), SHIFT, atol=0.05)
    assert np.linalg.norm(inner - SHIFT, axis=-1).mean() < 0.4
    # The reverse pair moves the other way.
    reverse = flow.estimate(pair[1], pair[0], method=method)[8:-8, 8:-8].reshape(-1, 2)
    np.testing.assert_allclose(np.median(reverse, axis=0), -SHIFT, atol=0.05)


def test_identical_images_have_no_flow(pair):
    still = flow.estimate(pair[0], pair[0])
    assert np.abs(still).max() < 0.05


def test_default_and_named_estimators_are_the_documented_functions(pair):
    np.testing.assert_array_equal(flow.estimate(*pair), flow.dis_flow(*pair))
    np.testing.assert_array_equal(
        flow.estimate(*pair, method="dis_fast"), flow.dis_flow(*pair, preset="fast")
    )
    np.testing.assert_array_equal(
        flow.estimate(*pair, method="farneback"), flow.farneback_flow(*pair)
    )
    # The presets differ, so the equalities above are not vacuous.
    assert not np.array_equal(flow.dis_flow(*pair), flow.dis_flow(*pair, preset="fast"))


def test_uint8_float_and_grey_inputs_give_the_same_flow(pair):
    image1, image2 = pair
    reference = flow.estimate(image1, image2)
    as_unit = [image / 255.0 for image in pair]  # [0, 1]
    as_contract = [image / 255.0 - 0.5 for image in pair]  # the example contract's range
    grey = [image[..., 0] for image in pair]  # [H, W]
    single_channel = [image[..., :1] for image in pair]  # [H, W, 1]
    for images in (as_unit, as_contract, grey, single_channel):
        np.testing.assert_array_equal(flow.estimate(*images), reference)


@pytest.mark.parametrize(
    "image1, image2, message",
    [
        (np.zeros((8, 8, 3), np.uint8), np.zeros((8, 9, 3), np.uint8), "same size"),
        (np.zeros((8, 8, 4), np.uint8), np.zeros((8, 8, 3), np.uint8), r"image1 must be \[H, W\]"),
        (np.zeros((8, 8, 3), np.uint8), np.zeros((2, 8, 8, 3), np.uint8), r"image2 must be"),
        (np.zeros((8, 8), np.int32), np.zeros((8, 8), np.uint8), "image1 must be uint8 or float"),
        (np.zeros((8, 8)), np.full((8, 8), np.nan), "image2 contains NaN"),
    ],
)
def test_bad_images_are_named(image1, image2, message):
    with pytest.raises(ValueError, match=message):
        flow.estimate(image1, image2)


def test_unknown_method_or_preset_lists_the_valid_ones(pair):
    with pytest.raises(ValueError, match=r"unknown flow estimator 'raft'.*'dis', 'dis_fast'"):
        flow.estimate(*pair, method="raft")
    with pytest.raises(ValueError, match=r"unknown DIS preset 'slow'.*'fast', 'medium'"):
        flow.dis_flow(*pair, preset="slow")


def test_geometric_flow_of_a_sideways_and_downward_camera_motion():
    # A plane at depth 2 seen by a camera that moves so that X2 = X1 + t: every pixel
    # moves by f * t / z, i.e. (9 * -0.5 / 2, 9.6 * 0.4 / 2) = (-2.25, 1.92) pixels.
    height, width = 8, 10
    intrinsics = np.array([0.9, 1.2, 0.5, 0.5])  # fx = 9, fy = 9.6 pixels
    depth = np.full((height, width), 2.0)
    depth[3, 4] = 0.0  # invalid depth: no flow, not valid
    translation = np.array([-0.5, 0.4, 0.0])
    exact, valid = flow.geometric_flow(depth, intrinsics, intrinsics, np.eye(3), translation)
    assert exact.dtype == np.float32 and exact.shape == (height, width, 2)
    expected = np.broadcast_to(np.array([-2.25, 1.92], np.float32), exact.shape).copy()
    expected[3, 4] = 0.0
    np.testing.assert_allclose(exact, expected, rtol=1e-6)
    # Valid where the pixel lands inside view 2: u - 2.25 > -0.5 and v + 1.92 < 7.5.
    columns, rows = np.arange(width) >= 2, np.arange(height) <= 5
    expected_valid = rows[:, None] & columns[None, :]
    expected_valid[3, 4] = False
    np.testing.assert_array_equal(valid, expected_valid)
    # With view 2's depth, a nearer surface where pixels land hides them.
    depth2 = np.full((height, width), 2.0)
    depth2[:, 6] = 1.0
    _, valid_with_depth2 = flow.geometric_flow(
        depth, intrinsics, intrinsics, np.eye(3), translation, depth2=depth2
    )
    # Column u lands on column rint(u - 2.25); those landing on column 6 are occluded.
    hidden = np.rint(np.arange(width) - 2.25) == 6
    np.testing.assert_array_equal(valid_with_depth2, expected_valid & ~hidden[None, :])
    assert hidden.sum() == 1


def test_endpoint_error_by_hand():
    estimate = np.zeros((2, 2, 2))
    truth = np.zeros((2, 2, 2))
    truth[0, 0] = [3.0, 4.0]  # error 5
    truth[0, 1] = [0.0, 1.0]  # error 1
    truth[1, 1] = [100.0, 0.0]  # error 100, but not valid
    valid = np.array([[True, True], [True, False]])
    assert flow.endpoint_error(estimate, truth, valid) == pytest.approx((5.0 + 1.0 + 0.0) / 3)
    assert np.isnan(flow.endpoint_error(estimate, truth, np.zeros((2, 2), bool)))
