"""Small Enc-Dec: the paper's reduced DispNet, sized like the global-local model.

Encoder: 4 convolutions with (16, 32, 54, 128) filters of sizes (7, 5, 3, 3), stride 2.
Decoder: 4 up-convolutions with (128, 64, 32, 16) filters of size 3 and stride 1,
each a x2 nearest-neighbour up-sampling followed by the convolution (the
"unpooling + convolution" up-convolution of FlowNet/DispNet); each decoder output is
concatenated with the encoder map of the same resolution (the input itself at
full resolution) before the next layer. A final 3x3 convolution predicts inverse
depth at full resolution. LeakyReLU everywhere; 8-channel pair + flow input.
"""

from __future__ import annotations

from collections.abc import Sequence

import flax.linen as nn
import jax
import jax.numpy as jnp

from gld.models import layers


def encode(
    inputs: jax.Array, features: Sequence[int], kernels: Sequence[int]
) -> tuple[jax.Array, list[jax.Array]]:
    """The stride-2 LeakyReLU encoder of the U-Nets (inside the caller's compact
    `__call__`; convolutions named encoder1, encoder2, ...).

    Returns:
      The bottleneck, and the skips for the decoder: the input, then every encoder map
      but the bottleneck (popped from the end, deepest first).
    """
    skips = [inputs]
    for index, (channels, kernel) in enumerate(zip(features, kernels, strict=True)):
        inputs = layers.Conv(
            channels, (kernel, kernel), strides=2, padding="SAME", name=f"encoder{index + 1}"
        )(inputs)
        inputs = layers.leaky_relu(inputs)
        skips.append(inputs)
    return inputs, skips[:-1]


def upsample_to(features: jax.Array, skip: jax.Array) -> jax.Array:
    """x2 nearest-neighbour up-sampling, cropped to the skip's size (ceil-halved maps can
    come back one pixel too large)."""
    features = jnp.repeat(jnp.repeat(features, 2, axis=1), 2, axis=2)
    return features[:, : skip.shape[1], : skip.shape[2]]


class SmallEncDec(nn.Module):
    """Reduced DispNet.

    Attributes:
      encoder_features: (16, 32, 54, 128).
      encoder_kernels: (7, 5, 3, 3).
      decoder_features: (128, 64, 32, 16).
      decoder_kernel: 3.
    """

    encoder_features: Sequence[int] = (16, 32, 54, 128)
    encoder_kernels: Sequence[int] = (7, 5, 3, 3)
    decoder_features: Sequence[int] = (128, 64, 32, 16)
    decoder_kernel: int = 3

    @nn.compact
    def __call__(
        self, image1: jax.Array, image2: jax.Array, flow: jax.Array, *, train: bool = False
    ) -> dict[str, jax.Array]:
        """Predicts inverse depth.

        Args:
          image1, image2: [B, H, W, 3] float32 in [-0.5, 0.5].
          flow: [B, H, W, 2] pixels, I1 -> I2.
          train: unused (no dropout or normalisation).

        Returns:
          'inv_depth', 'depth': [B, H, W].
        """
        del train
        if len(self.encoder_features) != len(self.decoder_features):
            raise ValueError(
                f"encoder and decoder need the same depth for the skips, got "
                f"{len(self.encoder_features)} and {len(self.decoder_features)} layers"
            )
        inputs = layers.network_inputs(image1, image2, flow)
        features, skips = encode(inputs, self.encoder_features, self.encoder_kernels)

        for index, channels in enumerate(self.decoder_features):
            skip = skips.pop()
            features = upsample_to(features, skip)
            features = layers.Conv(
                channels, (self.decoder_kernel,) * 2, name=f"decoder{index + 1}"
            )(features)
            features = jnp.concatenate([layers.leaky_relu(features), skip], axis=-1)
        logits = layers.Conv(1, (3, 3), name="prediction")(features)
        return layers.depth_outputs(logits)
