"""DispNet (Mayer et al., CVPR 2016): encoder-decoder with skips and six-scale predictions.

"A Large Dataset to Train Convolutional Networks for Disparity, Optical Flow, and
Scene Flow Estimation", DispNetSimple (Table 1 of that paper): a 7-level encoder
(conv1 ... conv6b, strides 2 down to 1/64), and a decoder of up-convolutions, each
fed the skip from the encoder level of the same resolution and the up-sampled
prediction of the coarser level. Predictions pr6 (1/64) ... pr1 (1/2) are all
returned; training puts the loss at every scale, as DispNet does. Adapted as in the
paper's appendix: 8-channel pair + flow input and LeakyReLU instead of ReLU.
"""

from __future__ import annotations

from collections.abc import Sequence

import flax.linen as nn
import jax
import jax.numpy as jnp

from gld.models import layers


def _crop_to(features: jax.Array, reference: jax.Array) -> jax.Array:
    """Crops [B, h, w, C] to the spatial size of `reference` (a x2 up-sampling of a
    ceil-halved map can be one pixel larger than the encoder map it joins)."""
    return features[:, : reference.shape[1], : reference.shape[2]]


class DispNet(nn.Module):
    """DispNetSimple.

    Attributes:
      encoder_features: channels of conv1, conv2, conv3a/b, conv4a/b, conv5a/b, conv6a/b
        (DispNet: 64, 128, 256, 512, 512, 1024; levels 3-6 have a stride-1 'b' conv).
      encoder_kernels: kernel sizes of conv1 ... conv6 (7, 5, 5, 3, 3, 3); 'b' convs are 3x3.
      decoder_features: channels of upconv5 ... upconv1 and iconv5 ... iconv1
        (512, 256, 128, 64, 32).
    """

    encoder_features: Sequence[int] = (64, 128, 256, 512, 512, 1024)
    encoder_kernels: Sequence[int] = (7, 5, 5, 3, 3, 3)
    decoder_features: Sequence[int] = (512, 256, 128, 64, 32)

    @nn.compact
    def __call__(
        self, image1: jax.Array, image2: jax.Array, flow: jax.Array, *, train: bool = False
    ) -> dict[str, jax.Array]:
        """Predicts inverse depth at six scales.

        Args:
          image1, image2: [B, H, W, 3] float32 in [-0.5, 0.5].
          flow: [B, H, W, 2] pixels, I1 -> I2.
          train: unused (DispNet has no dropout or normalisation).

        Returns:
          'inv_depth', 'depth': [B, H, W], pr1 (1/2 resolution) up-sampled bilinearly;
          'inv_depth_pyramid': (pr2, ..., pr6), [B, ceil(H/2^k), ceil(W/2^k)] for k = 2..6,
          finest first.
        """
        del train
        inputs = layers.network_inputs(image1, image2, flow)
        batch, height, width, _ = inputs.shape

        def conv(features, channels, kernel, stride, name):
            features = layers.Conv(
                channels, (kernel, kernel), strides=stride, padding="SAME", name=name
            )(features)
            return layers.leaky_relu(features)

        skips = []  # conv1, conv2, conv3b, conv4b, conv5b: the 1/2 ... 1/32 encoder maps.
        features = inputs
        for level, (channels, kernel) in enumerate(
            zip(self.encoder_features, self.encoder_kernels, strict=True), start=1
        ):
            suffix = "a" if level >= 3 else ""
            features = conv(features, channels, kernel, 2, f"conv{level}{suffix}")
            if level >= 3:
                features = conv(features, channels, 3, 1, f"conv{level}b")
            skips.append(features)
        skips.pop()  # conv6b is the bottleneck, not a skip.

        prediction = layers.Conv(1, (3, 3), name="pr6")(features)
        predictions = [prediction]
        for level, channels in zip(range(5, 0, -1), self.decoder_features, strict=True):
            skip = skips[level - 1]
            up_features = nn.ConvTranspose(
                channels, (4, 4), strides=(2, 2), padding="SAME", name=f"upconv{level}"
            )(features)
            up_features = _crop_to(layers.leaky_relu(up_features), skip)
            up_prediction = nn.ConvTranspose(
                1, (4, 4), strides=(2, 2), padding="SAME", name=f"upsample_pr{level + 1}"
            )(prediction)
            up_prediction = _crop_to(up_prediction, skip)
            features = jnp.concatenate([up_features, up_prediction, skip], axis=-1)
            features = conv(features, channels, 3, 1, f"iconv{level}")
            prediction = layers.Conv(1, (3, 3), name=f"pr{level}")(features)
            predictions.append(prediction)

        full_logits = jax.image.resize(prediction, (batch, height, width, 1), method="bilinear")
        outputs = layers.depth_outputs(full_logits)
        # predictions = [pr6, ..., pr1]; pr1 is the full-resolution output above.
        outputs["inv_depth_pyramid"] = tuple(
            layers.positive_inv_depth(logits[..., 0]) for logits in reversed(predictions[:-1])
        )
        return outputs
