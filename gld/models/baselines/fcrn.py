"""FCRN (Laina et al., 3DV 2016): ResNet-50 encoder + up-projection decoder.

"Deeper Depth Prediction with Fully Convolutional Residual Networks". The encoder
is ResNet-50 without its classifier (1/32 resolution, 2048 channels), followed by a
1x1 convolution to 1024 channels; four up-projection blocks (1024 -> 512 -> 256 ->
128 -> 64 channels) double the resolution each, and a 3x3 convolution predicts the
1/2-resolution map. Adapted as in the paper's appendix: 8-channel pair + flow input
and LeakyReLU instead of ReLU. It is trained from scratch: no ImageNet weights.

Batch normalisation keeps running statistics in the `batch_stats` collection; call
with `train=True, mutable=["batch_stats"]` to train, `train=False` to evaluate.
"""

from __future__ import annotations

import functools
from collections.abc import Sequence

import flax.linen as nn
import jax
import jax.numpy as jnp

from gld.models import layers


class Bottleneck(nn.Module):
    """ResNet bottleneck block: 1x1 -> 3x3 (strided) -> 1x1 (x4 channels), + shortcut."""

    features: int
    strides: int = 1

    @nn.compact
    def __call__(self, inputs: jax.Array, *, train: bool) -> jax.Array:
        norm = functools.partial(
            nn.BatchNorm, use_running_average=not train, momentum=0.9, epsilon=1e-5
        )
        residual = layers.Conv(self.features, (1, 1), use_bias=False)(inputs)
        residual = layers.leaky_relu(norm()(residual))
        residual = layers.Conv(
            self.features, (3, 3), strides=self.strides, padding="SAME", use_bias=False
        )(residual)
        residual = layers.leaky_relu(norm()(residual))
        residual = layers.Conv(self.features * 4, (1, 1), use_bias=False)(residual)
        # Zero-initialised last scale: each block starts as the identity (stable from scratch).
        residual = norm(scale_init=nn.initializers.zeros)(residual)
        shortcut = inputs
        if inputs.shape[-1] != self.features * 4 or self.strides != 1:
            shortcut = layers.Conv(
                self.features * 4, (1, 1), strides=self.strides, use_bias=False, name="projection"
            )(inputs)
            shortcut = norm(name="projection_norm")(shortcut)
        return layers.leaky_relu(residual + shortcut)


def unpool(features: jax.Array) -> jax.Array:
    """Laina's 2x2 un-pooling: each value goes to the top-left of a 2x2 block of zeros.

    Args:
      features: [B, h, w, C].

    Returns:
      [B, 2h, 2w, C].
    """
    batch, height, width, channels = features.shape
    zeros = jnp.zeros_like(features)
    rows = jnp.stack([features, zeros], axis=3)  # [B, h, w, 2, C]: column offset 0 / 1
    blocks = jnp.stack([rows, jnp.zeros_like(rows)], axis=2)  # [B, h, 2, w, 2, C]: row offset
    return blocks.reshape(batch, 2 * height, 2 * width, channels)


class UpProjection(nn.Module):
    """Up-projection block: unpool, then (5x5 conv, BN, act, 3x3 conv, BN) + (5x5 conv, BN)."""

    features: int

    @nn.compact
    def __call__(self, inputs: jax.Array, *, train: bool) -> jax.Array:
        norm = functools.partial(
            nn.BatchNorm, use_running_average=not train, momentum=0.9, epsilon=1e-5
        )
        unpooled = unpool(inputs)
        branch = layers.Conv(self.features, (5, 5), use_bias=False, name="conv5x5")(unpooled)
        branch = layers.leaky_relu(norm(name="norm5x5")(branch))
        branch = layers.Conv(self.features, (3, 3), use_bias=False, name="conv3x3")(branch)
        branch = norm(name="norm3x3")(branch)
        projection = layers.Conv(self.features, (5, 5), use_bias=False, name="projection")(unpooled)
        projection = norm(name="projection_norm")(projection)
        return layers.leaky_relu(branch + projection)


class FCRN(nn.Module):
    """ResNet-50 + up-projections.

    Attributes:
      stage_sizes: bottleneck blocks per ResNet stage ((3, 4, 6, 3) is ResNet-50).
      stem_features: channels of the 7x7 stride-2 stem (64); stage i has
        `stem_features * 2**i` bottleneck channels and 4x that many outputs.
      bridge_features: channels of the 1x1 convolution after the encoder (1024).
      up_features: channels of the up-projection blocks (512, 256, 128, 64).
      dropout_rate: dropout before the prediction conv in training (Laina: 0.5). 0 by
        default so that training needs no dropout key; with a rate > 0, pass
        `rngs={"dropout": key}` when `train=True`.
    """

    stage_sizes: Sequence[int] = (3, 4, 6, 3)
    stem_features: int = 64
    bridge_features: int = 1024
    up_features: Sequence[int] = (512, 256, 128, 64)
    dropout_rate: float = 0.0

    @nn.compact
    def __call__(
        self, image1: jax.Array, image2: jax.Array, flow: jax.Array, *, train: bool = False
    ) -> dict[str, jax.Array]:
        """Predicts inverse depth.

        Args:
          image1, image2: [B, H, W, 3] float32 in [-0.5, 0.5].
          flow: [B, H, W, 2] pixels, I1 -> I2.
          train: batch statistics (and dropout) in training, running averages otherwise.

        Returns:
          'inv_depth', 'depth': [B, H, W], the prediction at 1/32 * 2^len(up_features)
          resolution (1/2 for FCRN) up-sampled bilinearly.
        """
        inputs = layers.network_inputs(image1, image2, flow)
        batch, height, width, _ = inputs.shape
        norm = functools.partial(
            nn.BatchNorm, use_running_average=not train, momentum=0.9, epsilon=1e-5
        )

        features = layers.Conv(
            self.stem_features, (7, 7), strides=2, padding="SAME", use_bias=False, name="stem"
        )(inputs)
        features = layers.leaky_relu(norm(name="stem_norm")(features))
        features = nn.max_pool(features, (3, 3), strides=(2, 2), padding="SAME")
        for stage, num_blocks in enumerate(self.stage_sizes):
            for block in range(num_blocks):
                strides = 2 if stage > 0 and block == 0 else 1
                features = Bottleneck(
                    self.stem_features * 2**stage,
                    strides,
                    name=f"stage{stage + 1}_block{block + 1}",
                )(features, train=train)

        features = layers.Conv(self.bridge_features, (1, 1), use_bias=False, name="bridge")(
            features
        )
        features = norm(name="bridge_norm")(features)
        for index, channels in enumerate(self.up_features):
            features = UpProjection(channels, name=f"up_projection{index + 1}")(
                features, train=train
            )
        features = nn.Dropout(self.dropout_rate, deterministic=not train)(features)
        logits = layers.Conv(1, (3, 3), name="prediction")(features)
        logits = jax.image.resize(logits, (batch, height, width, 1), method="bilinear")
        return layers.depth_outputs(logits)
