"""Photometric self-supervision (monodepth2 / Struct2Depth family): inverse warping,
SSIM, the per-pixel minimum reprojection error with auto-masking, and the whole loss.

A pair gives one source frame per target: view 1 is the target (gld predicts view-1
depth), image 2 is warped into view 1 with the predicted view-1 depth and the predicted
pose 1 -> 2. The reverse direction (image 1 into view 2) would need view-2 depth, which
no gld model predicts, so it is not used.

With a single source frame, monodepth2's per-pixel minimum over sources is the minimum
between the reprojection error and the identity error (image 2 unwarped). Where the
identity error is the smaller, the pixel did not move between the views as the
predicted depth and pose say (a static camera, an object moving with it, a textureless
region); taking the identity error there is monodepth2's auto-mask, and such a pixel
gives no gradient. A pixel whose reprojection leaves image 2 or lands behind camera 2
is treated the same way, so pushing a pixel out of view can never lower the loss.

Conventions are gld.geometry's: `X2 = R @ X1 + t` maps camera 1 to camera 2, normalised
intrinsics `[fx/W, fy/H, cx/W, cy/H]`, pixel (u, v) with (0, 0) the centre of the
top-left pixel. Images are gld's: float in [-0.5, 0.5].
"""

from __future__ import annotations

import dataclasses
import math

import flax.linen as nn
import jax
import jax.numpy as jnp

from gld import geometry
from gld.losses import supervised as losses

# Weight of the SSIM term against L1 in the photometric error (monodepth2).
SSIM_WEIGHT = 0.85
# SSIM stabilisers for intensities in [0, 1]: (0.01 * 1)^2 and (0.03 * 1)^2.
_SSIM_C1 = 0.01**2
_SSIM_C2 = 0.03**2
# A reprojected point closer to camera 2 than this (in the depth's units) is invalid.
_MIN_PROJECTED_DEPTH = 1e-6
# Batch keys the self-supervised loss reads; without "intrinsics2" both views share
# view 1's camera.
REQUIRED_BATCH_KEYS = ("image1", "image2", "intrinsics1")
BATCH_KEYS = (*REQUIRED_BATCH_KEYS, "intrinsics2")
# Model outputs it reads: per-scale inverse depth in the units of the translation.
OUTPUT_KEYS = ("inv_depth_scales", "rotation", "translation")


@dataclasses.dataclass(frozen=True)
class SelfSupervisedWeights:
    """Weights of the self-supervised loss terms (monodepth2's defaults)."""

    photometric: float = 1.0
    smoothness: float = 1e-3

    def __post_init__(self):
        for field in dataclasses.fields(self):
            value = getattr(self, field.name)
            if not (math.isfinite(value) and value >= 0):
                raise ValueError(f"loss weight {field.name} must be finite and >= 0, got {value}")


def _check_shape(name: str, array: jax.Array, shape: tuple[int | None, ...]) -> None:
    """Raises ValueError naming `name` unless `array` has `shape` (None: any size)."""
    ok = array.ndim == len(shape) and all(
        want is None or have == want for have, want in zip(array.shape, shape, strict=True)
    )
    if not ok:
        wanted = "[" + ", ".join("*" if want is None else str(want) for want in shape) + "]"
        raise ValueError(f"{name} must have shape {wanted}, got {tuple(array.shape)}")


def sample_bilinear(image: jax.Array, pixels: jax.Array) -> jax.Array:
    """Differentiable bilinear lookup of `image` at `pixels`, edges replicated.

    Args:
      image: [B, H, W, C].
      pixels: [B, h, w, 2] (u, v) pixel-index coordinates into `image`.

    Returns:
      [B, h, w, C]; gradients flow to `image` and to `pixels` (inside the image).
    """
    batch, height, width, channels = image.shape
    # Clipping first keeps far-away (or huge, near-singular) coordinates integer-safe.
    u = jnp.clip(pixels[..., 0], 0.0, width - 1.0)
    v = jnp.clip(pixels[..., 1], 0.0, height - 1.0)
    u0 = jnp.floor(u)
    v0 = jnp.floor(v)
    weight_u = u - u0
    weight_v = v - v0
    u0 = u0.astype(jnp.int32)
    v0 = v0.astype(jnp.int32)
    u1 = jnp.minimum(u0 + 1, width - 1)
    v1 = jnp.minimum(v0 + 1, height - 1)
    flat = image.reshape(batch, height * width, channels)

    def gather(rows: jax.Array, columns: jax.Array) -> jax.Array:
        index = (rows * width + columns).reshape(batch, -1, 1)
        values = jnp.take_along_axis(flat, index, axis=1)
        return values.reshape(*rows.shape, channels)

    weight_u = weight_u[..., None]
    weight_v = weight_v[..., None]
    top = gather(v0, u0) * (1.0 - weight_u) + gather(v0, u1) * weight_u
    bottom = gather(v1, u0) * (1.0 - weight_u) + gather(v1, u1) * weight_u
    return top * (1.0 - weight_v) + bottom * weight_v


def _pixel_intrinsics(
    intrinsics: jax.Array, height: int, width: int
) -> tuple[jax.Array, jax.Array]:
    """Normalised intrinsics [B, 4] -> focal lengths and principal point in pixel-index
    coordinates, each [B, 1, 1, 2] (see `gld.geometry.intrinsics_matrix`)."""
    size = jnp.asarray([width, height], jnp.float32)
    focal = intrinsics[:, :2] * size
    principal = intrinsics[:, 2:] * size - 0.5
    return focal[:, None, None, :], principal[:, None, None, :]


def reproject(
    depth1: jax.Array,
    rotation: jax.Array,
    translation: jax.Array,
    intrinsics1: jax.Array,
    intrinsics2: jax.Array | None = None,
) -> tuple[jax.Array, jax.Array]:
    """Where each view-1 pixel lands in view 2, and whether that is a valid lookup.

    Args:
      depth1: [B, H, W] view-1 camera-z depth (positive).
      rotation, translation: [B, 3, 3], [B, 3]; X2 = R X1 + t.
      intrinsics1: [B, 4] normalised intrinsics of view 1.
      intrinsics2: [B, 4] of view 2; None means the same camera as view 1.

    Returns:
      pixels2 [B, H, W, 2] (u, v) in view 2 and valid [B, H, W] bool: in front of camera 2
      and inside image 2's area (-0.5 < u < W - 0.5, likewise v).
    """
    _check_shape("depth1", depth1, (None, None, None))
    batch, height, width = depth1.shape
    _check_shape("rotation", rotation, (batch, 3, 3))
    _check_shape("translation", translation, (batch, 3))
    _check_shape("intrinsics1", intrinsics1, (batch, 4))
    intrinsics2 = intrinsics1 if intrinsics2 is None else intrinsics2
    _check_shape("intrinsics2", intrinsics2, (batch, 4))
    # gld.geometry's projection, written out for normalised intrinsics: no matrix
    # inverse, which keeps the compiled gradient small.
    grid = geometry.pixel_grid(height, width, jnp)
    focal1, principal1 = _pixel_intrinsics(intrinsics1, height, width)
    focal2, principal2 = _pixel_intrinsics(intrinsics2, height, width)
    rays_xy = (grid - principal1) / focal1
    rays = jnp.concatenate([rays_xy, jnp.ones_like(rays_xy[..., :1])], axis=-1)
    points2 = geometry.transform_points(rays * depth1[..., None], rotation, translation)
    depth2 = points2[..., 2]
    safe_depth2 = jnp.where(depth2 > _MIN_PROJECTED_DEPTH, depth2, _MIN_PROJECTED_DEPTH)
    pixels2 = points2[..., :2] / safe_depth2[..., None] * focal2 + principal2
    u, v = pixels2[..., 0], pixels2[..., 1]
    # Inside the image's area (as `geometry.ground_truth_flow`); the outer half pixel
    # samples the edge pixel, which covers it.
    valid = (
        (depth2 > _MIN_PROJECTED_DEPTH)
        & (u > -0.5)
        & (u < width - 0.5)
        & (v > -0.5)
        & (v < height - 0.5)
    )
    return pixels2, valid


def warp_to_view1(
    image2: jax.Array,
    depth1: jax.Array,
    rotation: jax.Array,
    translation: jax.Array,
    intrinsics: jax.Array,
    intrinsics2: jax.Array | None = None,
) -> tuple[jax.Array, jax.Array]:
    """Inverse warping: image 2 seen from view 1, through view-1 depth and the pose.

    Depth and translation may share any scale: scaling both alike gives the same warp.

    Args:
      image2: [B, H, W, C].
      depth1: [B, H, W] view-1 camera-z depth (positive).
      rotation, translation: [B, 3, 3], [B, 3]; X2 = R X1 + t (camera 1 -> camera 2).
      intrinsics: [B, 4] normalised intrinsics of view 1.
      intrinsics2: [B, 4] of view 2; None means the same camera as view 1.

    Returns:
      warped [B, H, W, C] (bilinear, differentiable in every input; edge pixels repeated
      where the lookup leaves the image) and valid [B, H, W] bool: the point is in front
      of camera 2 and projects inside image 2.
    """
    _check_shape("image2", image2, (None, None, None, None))
    _check_shape("depth1", depth1, image2.shape[:3])
    pixels2, valid = reproject(depth1, rotation, translation, intrinsics, intrinsics2)
    return sample_bilinear(image2, pixels2), valid


def ssim(x: jax.Array, y: jax.Array) -> jax.Array:
    """Per-pixel structural similarity over 3x3 windows (monodepth2's).

    Images are shifted from gld's [-0.5, 0.5] to [0, 1], the range the constants assume;
    borders are reflection-padded; local statistics are 3x3 averages.

    Args:
      x, y: [B, H, W, C] in [-0.5, 0.5].

    Returns:
      [B, H, W, C] in [-1, 1]; 1 where the images agree.
    """
    if x.shape != y.shape:
        raise ValueError(f"ssim needs images of one shape, got {x.shape} and {y.shape}")
    x = x + 0.5
    y = y + 0.5
    # The five local statistics in one pooling (one op to compile and differentiate).
    statistics = jnp.concatenate([x, y, x * x, y * y, x * y], axis=-1)
    padded = jnp.pad(statistics, ((0, 0), (1, 1), (1, 1), (0, 0)), mode="reflect")
    local_means = nn.avg_pool(padded, (3, 3), strides=(1, 1), padding="VALID")
    mean_x, mean_y, mean_xx, mean_yy, mean_xy = jnp.split(local_means, 5, axis=-1)
    variance_x = mean_xx - mean_x**2
    variance_y = mean_yy - mean_y**2
    covariance = mean_xy - mean_x * mean_y
    numerator = (2 * mean_x * mean_y + _SSIM_C1) * (2 * covariance + _SSIM_C2)
    denominator = (mean_x**2 + mean_y**2 + _SSIM_C1) * (variance_x + variance_y + _SSIM_C2)
    return jnp.clip(numerator / denominator, -1.0, 1.0)


def photometric_error(a: jax.Array, b: jax.Array, alpha: float = SSIM_WEIGHT) -> jax.Array:
    """alpha * (1 - SSIM) / 2 + (1 - alpha) * |a - b|, averaged over channels.

    Args:
      a, b: [B, H, W, C] in [-0.5, 0.5].
      alpha: weight of the SSIM term.

    Returns:
      [B, H, W], 0 where the images agree.
    """
    structural = (1.0 - ssim(a, b)) / 2.0
    absolute = jnp.abs(a - b)
    return jnp.mean(alpha * structural + (1.0 - alpha) * absolute, axis=-1)


def minimum_reprojection_error(
    image1: jax.Array,
    image2: jax.Array,
    warped: jax.Array,
    valid: jax.Array,
    alpha: float = SSIM_WEIGHT,
) -> tuple[jax.Array, jax.Array]:
    """Per-pixel minimum of the reprojection and identity errors, with the auto-mask.

    Args:
      image1: [B, H, W, C] the target view.
      image2: [B, H, W, C] the source view, unwarped.
      warped: [B, H, W, C] image 2 warped into view 1.
      valid: [B, H, W] bool, where the warp looked inside image 2 (`warp_to_view1`).
      alpha: weight of the SSIM term.

    Returns:
      error [B, H, W] and auto_mask [B, H, W] bool: the pixels that take the identity
      error (it is no larger, or the warp is invalid there); they give no gradient.
    """
    identity = photometric_error(image2, image1, alpha)
    return _minimum_error(photometric_error(warped, image1, alpha), identity, valid)


def _minimum_error(
    reprojection: jax.Array, identity: jax.Array, valid: jax.Array
) -> tuple[jax.Array, jax.Array]:
    """Per-pixel minimum of two errors [B, H, W] and the auto-mask (see above)."""
    auto_mask = ~valid | (identity <= reprojection)
    return jnp.where(auto_mask, identity, reprojection), auto_mask


def mean_normalised(inv_depth: jax.Array) -> jax.Array:
    """Inverse depth [B, H, W] divided by its per-example mean (monodepth2), so that the
    smoothness term cannot be lowered by shrinking the depth scale."""
    return inv_depth / jnp.maximum(jnp.mean(inv_depth, axis=(1, 2), keepdims=True), 1e-7)


def self_supervised_loss(
    outputs: dict[str, jax.Array],
    batch: dict[str, jax.Array],
    weights: SelfSupervisedWeights = SelfSupervisedWeights(),
) -> tuple[jax.Array, dict[str, jax.Array]]:
    """The monodepth2 loss of a batch of pairs, with the contract of
    `gld.losses.supervised.total_loss`.

    For every scale s of `inv_depth_scales` (finest first): the inverse depth is
    up-sampled bilinearly to full resolution, image 2 is warped into view 1 with it and
    the predicted pose, and the per-pixel minimum reprojection error is averaged over
    all pixels; the edge-aware smoothness of the mean-normalised inverse depth at scale s,
    against image 1 resized to that scale, counts 1 / 2^s. Both are averaged over scales.

    Args:
      outputs: 'inv_depth_scales': sequence of [B, h_s, w_s] inverse depth in the units
        of 'translation' (full resolution first); 'rotation' [B, 3, 3] and 'translation'
        [B, 3], the predicted pose camera 1 -> camera 2.
      batch: 'image1', 'image2' [B, H, W, 3] in [-0.5, 0.5]; 'intrinsics1' [B, 4] and,
        when the views' cameras differ, 'intrinsics2' [B, 4].
      weights: the loss weights.

    Returns:
      (loss, terms) with the unweighted terms 'photometric', 'smoothness',
      'auto_mask_fraction' (pixels at full resolution, finest scale, that take the
      identity error, out-of-view ones included), 'out_of_view_fraction' and the
      weighted 'loss'.

    Raises:
      ValueError: naming missing output or batch keys, or an inconsistent shape.
    """
    missing_outputs = [key for key in OUTPUT_KEYS if key not in outputs]
    if missing_outputs:
        raise ValueError(
            f"self_supervised_loss needs model outputs {list(OUTPUT_KEYS)}; missing "
            f"{missing_outputs} (a model with a predicted pose, e.g. SelfSupervised)"
        )
    missing_batch = [key for key in REQUIRED_BATCH_KEYS if key not in batch]
    if missing_batch:
        raise ValueError(f"self_supervised_loss needs batch keys {missing_batch}")
    image1, image2 = batch["image1"], batch["image2"]
    _check_shape("image1", image1, (None, None, None, None))
    _check_shape("image2", image2, image1.shape)
    batch_size, height, width, channels = image1.shape
    scales = tuple(outputs["inv_depth_scales"])
    if not scales:
        raise ValueError("outputs['inv_depth_scales'] is empty")
    _check_shape("inv_depth_scales[0]", scales[0], (batch_size, height, width))

    full_inv_depths, smoothness_terms = [], []
    for scale, inv_depth in enumerate(scales):
        _check_shape(f"inv_depth_scales[{scale}]", inv_depth, (batch_size, None, None))
        scaled_image = image1
        if inv_depth.shape[1:] != (height, width):
            scaled_image = jax.image.resize(
                image1, (batch_size, *inv_depth.shape[1:], channels), "linear"
            )
            inv_depth_up = jax.image.resize(inv_depth, (batch_size, height, width), "linear")
        else:
            inv_depth_up = inv_depth
        full_inv_depths.append(inv_depth_up)
        smoothness = losses.edge_aware_smoothness(mean_normalised(inv_depth), scaled_image)
        smoothness_terms.append(smoothness / 2**scale)

    # Every scale's warp at once, the scales stacked along the batch axis (scale-major):
    # one warp and one SSIM in the compiled program instead of one per scale.
    num_scales = len(scales)

    def tiled(array: jax.Array) -> jax.Array:
        array = jnp.asarray(array)
        return jnp.tile(array, (num_scales,) + (1,) * (array.ndim - 1))

    intrinsics2 = batch.get("intrinsics2")
    warped, valid = warp_to_view1(
        tiled(image2),
        1.0 / jnp.concatenate(full_inv_depths, axis=0),
        tiled(outputs["rotation"]),
        tiled(outputs["translation"]),
        tiled(batch["intrinsics1"]),
        None if intrinsics2 is None else tiled(intrinsics2),
    )
    per_scale = (num_scales, batch_size, height, width)
    reprojection = photometric_error(warped, tiled(image1)).reshape(per_scale)
    identity = photometric_error(image2, image1)  # the same at every scale
    error, auto_mask = _minimum_error(reprojection, identity[None], valid.reshape(per_scale))
    auto_mask_fraction = jnp.mean(auto_mask[0].astype(jnp.float32))
    out_of_view_fraction = jnp.mean((~valid.reshape(per_scale)[0]).astype(jnp.float32))

    # Every scale has the same number of pixels: the mean is the mean of per-scale means.
    photometric = jnp.mean(error)
    smoothness = sum(smoothness_terms) / num_scales
    loss = weights.photometric * photometric + weights.smoothness * smoothness
    return loss, {
        "loss": loss,
        "photometric": photometric,
        "smoothness": smoothness,
        "auto_mask_fraction": auto_mask_fraction,
        "out_of_view_fraction": out_of_view_fraction,
    }
