"""Image resizing with numpy alone, equal to OpenCV's `INTER_AREA` and `INTER_LINEAR`.

Both are separable: one weight matrix per axis, [output size, input size], so a resize
is two matrix products. The predictors resize with these (`DepthPredictor` and the
exported runtime, `gld.inference.runtime`, which runs where OpenCV may be absent), so
both see the same pixels; `tests/gld/inference/test_resampling.py` checks them against
`cv2.resize` on float32 images, where OpenCV computes in floating point too.

* `area_weights` (OpenCV's `INTER_AREA`): shrinking both axes averages the input pixels
  each output pixel covers, weighted by the covered fraction; enlarging either axis
  interpolates linearly over the last fraction of each input pixel, along both axes
  (OpenCV's rule for zooming with `INTER_AREA`, close to nearest neighbour).
* `linear_weights` (`INTER_LINEAR`): bilinear with pixel centres aligned,
  x_in = (x_out + 0.5) * in / out - 0.5, clamped at the borders.
"""

from __future__ import annotations

import functools

import numpy as np


def _check_sizes(source: int, target: int) -> None:
    for name, value in (("source", source), ("target", target)):
        if not isinstance(value, int | np.integer) or value < 1:
            raise ValueError(f"{name} size must be a positive integer, got {value!r}")


def _interpolation(positions: np.ndarray, source: int) -> np.ndarray:
    """[len(positions), source] weights of linear interpolation at `positions` (input
    pixel-index coordinates), clamped to the outer pixels."""
    left = np.floor(positions).astype(np.int64)
    fraction = positions - left
    fraction = np.where(left < 0, 0.0, fraction)
    left = np.clip(left, 0, source - 1)
    fraction = np.where(left >= source - 1, 0.0, fraction)
    right = np.minimum(left + 1, source - 1)
    weights = np.zeros((len(positions), source), np.float64)
    rows = np.arange(len(positions))
    np.add.at(weights, (rows, left), 1.0 - fraction)
    np.add.at(weights, (rows, right), fraction)
    return weights


@functools.lru_cache(maxsize=64)
def area_weights(source: int, target: int, averaging: bool = True) -> np.ndarray:
    """[target, source] float32 weights of OpenCV's `INTER_AREA` along one axis.

    `averaging`: whether OpenCV averages along this axis, which it does when neither axis
    is enlarged (`resize` decides); otherwise both axes follow the enlarging rule.
    """
    _check_sizes(source, target)
    # As OpenCV: the scale is the inverse of target / source (which can differ from
    # source / target in the last bit, and so move a floor).
    inverse = target / source
    scale = 1.0 / inverse
    if averaging:
        if scale < 1.0:
            raise ValueError(f"averaging cannot enlarge ({source} -> {target})")
        # Output pixel i covers input [i * scale, (i + 1) * scale): overlap with each pixel.
        starts = np.arange(target) * scale
        ends = starts + scale
        pixels = np.arange(source)
        overlap = np.minimum(ends[:, None], pixels[None] + 1) - np.maximum(starts[:, None], pixels)
        weights = np.clip(overlap, 0.0, None) / scale
    else:
        # Otherwise OpenCV interpolates between input pixels floor(i * scale) and the
        # next one with the fraction of the output pixel that lies past the first's end.
        index = np.arange(target)
        left = np.floor(index * scale)
        fraction = (index + 1) - (left + 1) * inverse
        fraction = np.where(fraction <= 0, 0.0, fraction - np.floor(fraction))
        weights = _interpolation(left + fraction, source)
    weights = weights.astype(np.float32)
    weights.flags.writeable = False
    return weights


@functools.lru_cache(maxsize=64)
def linear_weights(source: int, target: int) -> np.ndarray:
    """[target, source] float32 weights of OpenCV's `INTER_LINEAR` along one axis."""
    _check_sizes(source, target)
    positions = (np.arange(target) + 0.5) * (source / target) - 0.5
    weights = _interpolation(positions, source).astype(np.float32)
    weights.flags.writeable = False
    return weights


def resize(images: np.ndarray, height: int, width: int, method: str = "area") -> np.ndarray:
    """Images [B, H, W, C] or maps [B, H, W] resized to height x width, float32.

    Args:
      images: float [B, H, W, C] or [B, H, W].
      height, width: the output size.
      method: "area" (OpenCV's INTER_AREA) or "linear" (INTER_LINEAR).
    """
    weights_of = {"area": area_weights, "linear": linear_weights}
    if method not in weights_of:
        raise ValueError(f"method must be one of {sorted(weights_of)}, got {method!r}")
    images = np.asarray(images, np.float32)
    if images.ndim not in (3, 4):
        raise ValueError(f"images must be [B, H, W, C] or [B, H, W], got shape {images.shape}")
    in_height, in_width = images.shape[1:3]
    if (in_height, in_width) == (height, width):
        return images.copy()
    if method == "area":
        averaging = in_height >= height and in_width >= width
        rows = area_weights(in_height, height, averaging)
        columns = area_weights(in_width, width, averaging)
    else:
        rows, columns = linear_weights(in_height, height), linear_weights(in_width, width)
    # Rows: [h, H] x [B, H, W*C]; columns: [B, h, C, W] x [W, w].
    resized = np.matmul(rows, images.reshape(len(images), in_height, -1))
    if images.ndim == 3:
        return np.matmul(resized, columns.T)
    channels = images.shape[-1]
    resized = resized.reshape(len(images), height, in_width, channels).transpose(0, 1, 3, 2)
    return np.ascontiguousarray(np.matmul(resized, columns.T).transpose(0, 1, 3, 2))


def model_images(
    images: np.ndarray, box: tuple[int, int, int, int], height: int, width: int
) -> np.ndarray:
    """[B, H, W, C] inputs -> their crop `box` (top, left, height, width; `inputs.crop_box`)
    resized by area to the model's height x width, float32."""
    top, left, crop_height, crop_width = box
    cropped = np.asarray(images)[:, top : top + crop_height, left : left + crop_width]
    return resize(cropped, height, width, "area")


def model_frames(
    frames: np.ndarray, box: tuple[int, int, int, int], height: int, width: int
) -> np.ndarray:
    """`model_images` of frames in [0, 1], kept in [0, 1] (the weights' float rounding can
    leave a value a few ulp outside)."""
    return np.clip(model_images(frames, box, height, width), 0.0, 1.0)


def depth_at_input(
    inv_depth: np.ndarray, box: tuple[int, int, int, int], in_height: int, in_width: int
) -> np.ndarray:
    """[B, h, w] inverse depth at the model's size -> [B, in_height, in_width] depth at
    the input's: inverse depth resized linearly to the crop `box`, inverted, NaN outside."""
    top, left, crop_height, crop_width = box
    depth = np.full((len(inv_depth), in_height, in_width), np.nan, np.float32)
    resized = resize(inv_depth, crop_height, crop_width, "linear")
    depth[:, top : top + crop_height, left : left + crop_width] = 1.0 / resized
    return depth
