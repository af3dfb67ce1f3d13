"""The global module G(I1, I2, w) -> global parameters g [B, 6]."""

from __future__ import annotations

from collections.abc import Sequence

import flax.linen as nn
import jax
import jax.numpy as jnp

from gld.models import layers

ENCODER_NORMS = ("none", "instance")


class GlobalEncoder(nn.Module):
    """Convolutional encoder with global average pooling (the paper's global module).

    Five 3x3 conv layers with LeakyReLU (channels 16..256, stride 2 in the first four),
    a 3x3 conv to `global_dim` channels, then the spatial mean.

    `norm="instance"` standardises each hidden channel over the image, per example
    (with a learned scale and offset), before each activation; the paper's encoder has
    no normalisation (`norm="none"`).

    Attributes:
      channels: output channels of the hidden conv layers.
      strides: stride of each hidden conv layer.
      global_dim: size of the global parameter vector g.
      kernel_size: spatial size of every conv kernel.
      norm: "none" (the paper's) or "instance" (see above).
    """

    channels: Sequence[int] = (16, 32, 64, 128, 256)
    strides: Sequence[int] = (2, 2, 2, 2, 1)
    global_dim: int = 6
    kernel_size: int = 3
    norm: str = "none"

    @nn.compact
    def __call__(self, inputs: jax.Array) -> jax.Array:
        """Encodes the stacked inputs.

        Args:
          inputs: [B, H, W, C] (image pair and normalised flow, 8 channels, by default).

        Returns:
          global_params: [B, global_dim].
        """
        if len(self.channels) != len(self.strides):
            raise ValueError(
                f"channels {tuple(self.channels)} and strides {tuple(self.strides)} "
                "differ in length"
            )
        if self.norm not in ENCODER_NORMS:
            raise ValueError(f"norm must be one of {ENCODER_NORMS}, got {self.norm!r}")
        kernel = (self.kernel_size, self.kernel_size)
        # lax's convs, not `layers.Conv`'s patches: as patches, the last two convs' float32
        # rounding differed more between one device and four, and the pose refinement
        # after them carried it into the hypernetwork (its kernel 3.4e-5 apart after two
        # steps of a test, against 6e-6 with lax); nor was the main job's step faster.
        features = inputs
        for index, (channels, stride) in enumerate(zip(self.channels, self.strides, strict=True)):
            features = nn.Conv(channels, kernel, strides=stride, name=f"conv{index}")(features)
            if self.norm == "instance" and features.shape[1] * features.shape[2] < 2:
                raise ValueError(
                    f"conv{index} of the global encoder outputs a 1x1 map for inputs of "
                    f"{inputs.shape[1]}x{inputs.shape[2]}: instance normalisation would "
                    "zero it; use larger inputs, fewer strides or norm='none'"
                )
            if self.norm == "instance":
                features = nn.GroupNorm(num_groups=None, group_size=1, name=f"norm{index}")(
                    features
                )
            features = layers.leaky_relu(features)
        features = nn.Conv(self.global_dim, kernel, name="to_global")(features)
        return jnp.mean(features, axis=(1, 2))
