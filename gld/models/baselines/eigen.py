"""Eigen et al. (NIPS 2014): a coarse, fully connected global network + a fine local network.

"Depth Map Prediction from a Single Image using a Multi-Scale Deep Network". The
coarse network sees the whole image through five convolutions and two fully
connected layers and predicts a 1/4-resolution map; the fine network refines it
with three convolutions at 1/4 resolution. Adapted as in the paper's appendix: the
input is the 8-channel pair + flow, every ReLU is a LeakyReLU, and both networks
are trained jointly (the coarse map is returned in `inv_depth_pyramid`, so it is
supervised like Eigen's first training stage). The dense layers depend on the
input size; Flax infers their input width from the input at `init`.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import flax.linen as nn
import jax
import jax.numpy as jnp

from gld.models import layers


class EigenNet(nn.Module):
    """Coarse + fine depth network.

    Attributes:
      coarse_features: channels of coarse convolutions 1-5 (Eigen: 96, 256, 384, 384, 256).
      coarse_kernels: their kernel sizes (11, 5, 3, 3, 3); the first has stride 4.
      coarse_pooled: which coarse layers are followed by 2x2 max pooling (1, 2 and 5).
      hidden_units: width of the fully connected hidden layer (4096).
      fine_features: channels of fine convolutions 1 and 3 (63, 64).
      fine_kernels: kernel sizes of fine convolutions 1, 3 and 4 (9, 5, 5).
      dropout_rate: dropout after the hidden layer in training (Eigen: 0.5); with a
        rate > 0, `train=True` needs `rngs={"dropout": key}` (gld's trainer passes one).
    """

    coarse_features: Sequence[int] = (96, 256, 384, 384, 256)
    coarse_kernels: Sequence[int] = (11, 5, 3, 3, 3)
    coarse_pooled: Sequence[bool] = (True, True, False, False, True)
    hidden_units: int = 4096
    fine_features: Sequence[int] = (63, 64)
    fine_kernels: Sequence[int] = (9, 5, 5)
    dropout_rate: float = 0.5

    @nn.compact
    def __call__(
        self, image1: jax.Array, image2: jax.Array, flow: jax.Array, *, train: bool = False
    ) -> dict[str, jax.Array]:
        """Predicts inverse depth.

        Args:
          image1, image2: [B, H, W, 3] float32 in [-0.5, 0.5].
          flow: [B, H, W, 2] pixels, I1 -> I2.
          train: enables dropout.

        Returns:
          'inv_depth', 'depth': [B, H, W] (the fine prediction upsampled bilinearly);
          'inv_depth_pyramid': ([B, ceil(H/4), ceil(W/4)],) the coarse prediction.
        """
        inputs = layers.network_inputs(image1, image2, flow)
        batch, height, width, _ = inputs.shape
        out_height, out_width = math.ceil(height / 4), math.ceil(width / 4)

        # Coarse (global) network.
        features = inputs
        for index, (channels, kernel, pooled) in enumerate(
            zip(self.coarse_features, self.coarse_kernels, self.coarse_pooled, strict=True)
        ):
            stride = 4 if index == 0 else 1
            features = layers.Conv(
                channels,
                (kernel, kernel),
                strides=stride,
                padding="SAME",
                name=f"coarse{index + 1}",
            )(features)
            features = layers.leaky_relu(features)
            if pooled:
                features = nn.max_pool(features, (2, 2), strides=(2, 2), padding="SAME")
        features = features.reshape(batch, -1)
        features = layers.leaky_relu(nn.Dense(self.hidden_units, name="coarse6")(features))
        features = nn.Dropout(self.dropout_rate, deterministic=not train)(features)
        coarse_logits = nn.Dense(out_height * out_width, name="coarse7")(features)
        coarse_logits = coarse_logits.reshape(batch, out_height, out_width, 1)

        # Fine (local) network at 1/4 resolution, fed the coarse map.
        fine = layers.Conv(
            self.fine_features[0],
            (self.fine_kernels[0],) * 2,
            strides=2,
            padding="SAME",
            name="fine1",
        )(inputs)
        fine = layers.leaky_relu(fine)
        fine = nn.max_pool(fine, (2, 2), strides=(2, 2), padding="SAME")
        fine = jnp.concatenate([fine, coarse_logits], axis=-1)
        fine = layers.Conv(self.fine_features[1], (self.fine_kernels[1],) * 2, name="fine3")(fine)
        fine = layers.leaky_relu(fine)
        fine_logits = layers.Conv(1, (self.fine_kernels[2],) * 2, name="fine4")(fine)

        full_logits = jax.image.resize(fine_logits, (batch, height, width, 1), method="bilinear")
        outputs = layers.depth_outputs(full_logits)
        outputs["inv_depth_pyramid"] = (layers.positive_inv_depth(coarse_logits[..., 0]),)
        return outputs
