"""numpy resizing (gld/inference/resampling.py) against OpenCV's, which it replaces."""

import cv2
import numpy as np
import pytest

from gld.inference import resampling

# (input height, width) -> (output height, width): shrinking by integer and fractional
# factors, enlarging, one axis each way, sizes that move OpenCV's floor, and one pixel.
SIZES = [
    ((480, 640), (96, 128)),
    ((100, 130), (24, 32)),
    ((37, 51), (24, 32)),
    ((60, 70), (150, 50)),
    ((100, 130), (150, 50)),
    ((100, 130), (97, 131)),
    ((200, 90), (96, 128)),
    ((7, 3), (24, 32)),
    ((1, 5), (1, 1)),
]


@pytest.mark.parametrize("source, target", SIZES)
@pytest.mark.parametrize("method", ["area", "linear"])
def test_resize_equals_opencv_on_float_images(source, target, method):
    rng = np.random.default_rng(sum(source) + sum(target))
    images = rng.random((2, *source, 3)).astype(np.float32)
    flag = {"area": cv2.INTER_AREA, "linear": cv2.INTER_LINEAR}[method]
    got = resampling.resize(images, *target, method)
    assert got.shape == (2, *target, 3) and got.dtype == np.float32
    for image, resized in zip(images, got, strict=True):
        expected = cv2.resize(image, target[::-1], interpolation=flag)
        np.testing.assert_allclose(resized, expected, atol=1e-5)
    # Maps without channels too.
    maps = images[..., 0]
    expected = cv2.resize(maps[1], target[::-1], interpolation=flag)
    np.testing.assert_allclose(resampling.resize(maps, *target, method)[1], expected, atol=1e-5)


def test_crops_resize_and_depth_comes_back_with_nan_outside_the_crop():
    rng = np.random.default_rng(0)
    frames = rng.random((1, 40, 90, 3)).astype(np.float32)
    box = (0, 15, 40, 60)  # the centred crop of a 2:3 model
    resized = resampling.model_frames(frames, box, 24, 36)
    expected = cv2.resize(frames[0, :, 15:75], (36, 24), interpolation=cv2.INTER_AREA)
    np.testing.assert_allclose(resized[0], expected, atol=1e-5)
    assert resized.min() >= 0.0 and resized.max() <= 1.0
    inv_depth = 0.5 + rng.random((1, 24, 36)).astype(np.float32)
    depth = resampling.depth_at_input(inv_depth, box, 40, 90)
    assert np.isnan(depth[0, :, :15]).all() and np.isnan(depth[0, :, 75:]).all()
    expected = 1.0 / cv2.resize(inv_depth[0], (60, 40), interpolation=cv2.INTER_LINEAR)
    np.testing.assert_allclose(depth[0, :, 15:75], expected, rtol=1e-5)


def test_bad_arguments_are_refused():
    with pytest.raises(ValueError, match="method must be one of"):
        resampling.resize(np.zeros((1, 4, 4)), 2, 2, "cubic")
    with pytest.raises(ValueError, match=r"images must be \[B, H, W, C\] or \[B, H, W\]"):
        resampling.resize(np.zeros((4, 4)), 2, 2)
    with pytest.raises(ValueError, match="target size must be a positive integer"):
        resampling.area_weights(4, 0)
