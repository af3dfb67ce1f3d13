"""A learned optical-flow network in the style of PWC-Net (Sun et al., CVPR 2018).

`FlowNet(image1, image2)` estimates flow I1 -> I2 in pixels, as `gld.flow`'s classical
estimators do: a feature pyramid shared by both images (strided 3x3 convolutions,
LeakyReLU), then, from the coarsest level to `finest_level`, the second image's features
warped by the upsampled flow of the level below (`warp`), a local cost volume of cosine
similarities (`correlation` of `unit_features`), and a small convolutional estimator
that refines the flow from [cost volume, image-1 features, upsampled flow]. A context
network of dilated convolutions refines the finest estimate, which is upsampled
bilinearly to the input's resolution (`upsample_flow`).

Images must be [B, H, W, 3] with H and W divisible by 2**levels (levels = the length of
`feature_channels`; 16 by default: 64x48, 128x96 and 256x192 all qualify); other sizes
are refused with a ValueError rather than padded, so every level's grid lines up exactly
with the input's pixels.

Inside the network each level's flow is in that level's own pixels; every output is in
pixels of the input images.
"""

from __future__ import annotations

from collections.abc import Sequence

import flax.linen as nn
import jax
import jax.numpy as jnp

from gld.models.layers import Conv, leaky_relu
from gld.options import option


def check_architecture(
    feature_channels: Sequence[int],
    estimator_channels: Sequence[int],
    context_channels: Sequence[int],
    max_displacement: int,
    finest_level: int,
) -> None:
    """Raises ValueError naming the first architecture option out of range."""
    for name, values, allow_empty in (
        ("feature_channels", feature_channels, False),
        ("estimator_channels", estimator_channels, False),
        ("context_channels", context_channels, True),
    ):
        if (not values and not allow_empty) or any(int(value) < 1 for value in values):
            raise ValueError(f"{name} must be positive integers, got {list(values)}")
    if max_displacement < 1:
        raise ValueError(f"max_displacement must be >= 1, got {max_displacement}")
    if not 1 <= finest_level <= len(feature_channels):
        raise ValueError(
            f"finest_level must be in [1, {len(feature_channels)}] (the pyramid's levels), "
            f"got {finest_level}"
        )


def check_image_pair(image1: jax.Array, image2: jax.Array, levels: int) -> None:
    """Raises ValueError unless both images are [B, H, W, 3] of one shape with H and W
    divisible by 2**levels."""
    if image1.shape != image2.shape:
        raise ValueError(
            f"image1 and image2 must have the same shape, got {image1.shape} and {image2.shape}"
        )
    if image1.ndim != 4 or image1.shape[-1] != 3:
        raise ValueError(f"images must be [B, H, W, 3], got shape {image1.shape}")
    height, width = image1.shape[1:3]
    multiple = 2**levels
    if height % multiple or width % multiple:
        raise ValueError(
            f"image size {width}x{height} (WxH) is not divisible by {multiple} = 2**levels "
            f"of the feature pyramid ({levels} levels); crop or resize the images, or use "
            "fewer feature_channels"
        )


# ---------------------------------------------------------------------- pure functions


def warp(features: jax.Array, flow: jax.Array) -> jax.Array:
    """Backward warp: `features` sampled bilinearly at p + flow(p) for every pixel p.

    Differentiable in both arguments. Neighbours outside the map contribute zero, so a
    lookup that leaves the map fades to zero (no information rather than a repeated
    border).

    Args:
      features: [B, H, W, C], e.g. image 2's features.
      flow: [B, H, W, 2] in pixels of this map, (u, v) = (right, down).

    Returns:
      [B, H, W, C]: at p, the features of the second map at p + flow(p).
    """
    batch, height, width, channels = features.shape
    u = jnp.arange(width, dtype=flow.dtype)[None, None, :] + flow[..., 0]
    v = jnp.arange(height, dtype=flow.dtype)[None, :, None] + flow[..., 1]
    u0, v0 = jnp.floor(u), jnp.floor(v)
    weight_u, weight_v = u - u0, v - v0
    # The four neighbours of every lookup, gathered at once: [B, 4, H, W].
    u_taps = jnp.stack([u0, u0 + 1, u0, u0 + 1], axis=1)
    v_taps = jnp.stack([v0, v0, v0 + 1, v0 + 1], axis=1)
    weights = jnp.stack(
        [
            (1 - weight_u) * (1 - weight_v),
            weight_u * (1 - weight_v),
            (1 - weight_u) * weight_v,
            weight_u * weight_v,
        ],
        axis=1,
    )
    inside = (u_taps >= 0) & (u_taps <= width - 1) & (v_taps >= 0) & (v_taps <= height - 1)
    indices = (
        jnp.clip(v_taps, 0, height - 1).astype(jnp.int32) * width
        + jnp.clip(u_taps, 0, width - 1).astype(jnp.int32)
    ).reshape(batch, -1)
    flat = features.reshape(batch, height * width, channels)
    values = jax.vmap(lambda rows, index: rows[index])(flat, indices)
    values = values.reshape(batch, 4, height, width, channels)
    return jnp.sum(values * jnp.where(inside, weights, 0.0)[..., None], axis=1)


def correlation(features1: jax.Array, features2: jax.Array, max_displacement: int) -> jax.Array:
    """The local cost volume: dot products of features1 at p with features2 at
    p + (du, dv) for |du|, |dv| <= max_displacement (zero beyond the map's border).

    Args:
      features1, features2: [B, H, W, C] (`FlowNet` gives unit vectors: cosine costs).
      max_displacement: d >= 1.

    Returns:
      [B, H, W, (2d + 1)**2]; channel (dv + d) * (2d + 1) + (du + d) holds displacement
      (du, dv), so the centre channel (2d + 1)**2 // 2 is zero displacement.
    """
    d = max_displacement
    size = 2 * d + 1
    padded = jnp.pad(features2, ((0, 0), (d, d), (d, d), (0, 0)))

    def cost(index: jax.Array) -> jax.Array:
        shifted = jax.lax.dynamic_slice(
            padded, (0, index // size, index % size, 0), features1.shape
        )
        return jnp.sum(features1 * shifted, axis=-1)

    # A loop over the displacements: XLA compiles one body instead of (2d + 1)**2 slices
    # (seconds less per level) and it runs as fast on CPU.
    return jnp.moveaxis(jax.lax.map(cost, jnp.arange(size * size)), 0, -1)


def unit_features(features: jax.Array, epsilon: float = 1e-6) -> jax.Array:
    """Features [..., C] scaled to unit length per pixel (a zero vector stays zero)."""
    return features * jax.lax.rsqrt(jnp.sum(features**2, axis=-1, keepdims=True) + epsilon)


def upsample_flow(flow: jax.Array, factor: int) -> jax.Array:
    """Flow [B, h, w, 2] in its map's pixels -> [B, h * factor, w * factor, 2] in pixels
    of the finer map: bilinear (`jax.image.resize`, pixel centres at half-pixel offsets)
    and scaled by `factor`."""
    if factor == 1:
        return flow
    batch, height, width, _ = flow.shape
    resized = jax.image.resize(flow, (batch, height * factor, width * factor, 2), "bilinear")
    return resized * factor


# ---------------------------------------------------------------------------- modules


class FeaturePyramid(nn.Module):
    """Per level: a stride-2 3x3 conv and a 3x3 conv, LeakyReLU after each.

    Returns a list, finest first: level l (1-based) is [B, H / 2**l, W / 2**l, C_l].
    """

    channels: Sequence[int]

    @nn.compact
    def __call__(self, images: jax.Array) -> list[jax.Array]:
        features, x = [], images
        for level, channels in enumerate(self.channels, start=1):
            x = leaky_relu(Conv(channels, (3, 3), strides=2, name=f"level{level}_down")(x))
            x = leaky_relu(Conv(channels, (3, 3), name=f"level{level}_conv")(x))
            features.append(x)
        return features


class FlowEstimator(nn.Module):
    """3x3 convs with LeakyReLU, then a linear 3x3 conv to the flow update.

    Returns (flow update [B, h, w, 2], the last hidden features [B, h, w, C])."""

    channels: Sequence[int]

    @nn.compact
    def __call__(self, inputs: jax.Array) -> tuple[jax.Array, jax.Array]:
        x = inputs
        for index, channels in enumerate(self.channels):
            x = leaky_relu(Conv(channels, (3, 3), name=f"conv{index}")(x))
        return Conv(2, (3, 3), name="flow")(x), x


class ContextNetwork(nn.Module):
    """Dilated 3x3 convs (dilations 1, 2, 4, 8, ..., growing the receptive field
    cheaply) on [estimator features, flow] -> a flow update [B, h, w, 2]."""

    channels: Sequence[int]

    @nn.compact
    def __call__(self, inputs: jax.Array) -> jax.Array:
        x = inputs
        for index, channels in enumerate(self.channels):
            dilation = 2 ** min(index, 3)
            x = leaky_relu(Conv(channels, (3, 3), kernel_dilation=dilation, name=f"conv{index}")(x))
        return Conv(2, (3, 3), name="flow")(x)


class FlowNet(nn.Module):
    """Coarse-to-fine flow: pyramid, warp, cost volume, estimator per level, context.

    Attributes:
      feature_channels: channels per pyramid level, finest first.
      estimator_channels: convolutions of each level's estimator.
      context_channels: the context network's convolutions (empty: none).
      max_displacement: the cost volume's reach per level, in that level's pixels.
      finest_level: the finest estimated level (1-based; 1 = half resolution).
    """

    feature_channels: Sequence[int] = option(
        (16, 32, 48, 64),
        "Channels of each feature-pyramid level, finest first; one level per entry, each "
        "halving the resolution (inputs must be divisible by 2**levels).",
        at_least=1,
    )
    estimator_channels: Sequence[int] = option(
        (48, 32, 16), "Channels of the convolutions of each level's flow estimator.", at_least=1
    )
    context_channels: Sequence[int] = option(
        (32, 32, 32, 16),
        "Channels of the context network's dilated convolutions at the finest estimated "
        "level (dilations 1, 2, 4, 8, ...); empty: no context network.",
        at_least=1,
        may_be_empty=True,
    )
    max_displacement: int = option(
        4,
        "Largest displacement (feature pixels) of the correlation cost volume at each "
        "level: (2d + 1)**2 channels.",
        at_least=1,
    )
    finest_level: int = option(
        2,
        "The finest level whose flow is estimated (1 = half resolution); the output is its "
        "flow upsampled by 2**finest_level.",
        at_least=1,
    )

    @property
    def levels(self) -> int:
        return len(self.feature_channels)

    @nn.compact
    def __call__(self, image1: jax.Array, image2: jax.Array) -> dict[str, jax.Array]:
        """Flow I1 -> I2.

        Args:
          image1, image2: [B, H, W, 3] float (gld's contract: [-0.5, 0.5]); H and W
            divisible by 2**levels.

        Returns:
          "flow": [B, H, W, 2] pixels, I1 -> I2 (pixel p of image 1 sits at p + flow(p)
            in image 2);
          "flow_pyramid": the estimate of every level, coarsest first: level l is
            [B, H / 2**l, W / 2**l, 2] in pixels of the input images (the context
            network's refinement included at `finest_level`).
        """
        check_architecture(
            self.feature_channels,
            self.estimator_channels,
            self.context_channels,
            self.max_displacement,
            self.finest_level,
        )
        check_image_pair(image1, image2, self.levels)
        batch = image1.shape[0]
        # One pass over both images: the pyramid's weights are shared.
        pyramid = FeaturePyramid(tuple(self.feature_channels), name="pyramid")(
            jnp.concatenate([image1, image2], axis=0)
        )
        flow = None
        flow_pyramid = []
        for level in range(self.levels, self.finest_level - 1, -1):
            features1, features2 = pyramid[level - 1][:batch], pyramid[level - 1][batch:]
            if flow is None:
                upsampled = jnp.zeros((*features1.shape[:3], 2), features1.dtype)
                warped = features2
            else:
                upsampled = upsample_flow(flow, 2)
                warped = warp(features2, upsampled)
            # Cosine costs: in [-1, 1] whatever the features' scale, so the estimator can
            # use them from the first steps (raw products of freshly initialised
            # features are tiny and training from scratch stalled at zero flow).
            cost = leaky_relu(
                correlation(unit_features(features1), unit_features(warped), self.max_displacement)
            )
            update, hidden = FlowEstimator(tuple(self.estimator_channels), name=f"level{level}")(
                jnp.concatenate([cost, features1, upsampled], axis=-1)
            )
            flow = upsampled + update
            if level == self.finest_level and self.context_channels:
                flow = flow + ContextNetwork(tuple(self.context_channels), name="context")(
                    jnp.concatenate([hidden, flow], axis=-1)
                )
            flow_pyramid.append(flow * 2**level)
        return {
            "flow": upsample_flow(flow, 2**self.finest_level),
            "flow_pyramid": flow_pyramid,
        }


def init_params(model: FlowNet, seed: int) -> dict:
    """Initial parameters of `model` (they do not depend on the image size).

    Drawn with an "rbg" key (XLA's RngBitGenerator): the initialisers then compile in
    seconds on a CPU, where threefry keys take tens of seconds for this many layers. The
    values are reproducible for a seed on one platform, not across CPU and GPU.
    """
    side = 2 ** len(model.feature_channels)
    images = jax.ShapeDtypeStruct((1, side, side, 3), jnp.float32)
    key = jax.random.key(seed, impl="rbg")
    return jax.jit(model.init)(key, images, images)["params"]


def parameter_count(params) -> int:
    """Number of parameters of a variable tree."""
    return sum(int(leaf.size) for leaf in jax.tree_util.tree_leaves(params))
