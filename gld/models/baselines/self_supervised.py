"""A self-supervised depth baseline (Struct2Depth / monodepth2 family), sized for CPU.

Two networks trained together by photometric consistency (`gld.losses.photometric`), without
any depth supervision:

* Depth network: a U-Net on image 1 (monodepth2's depth net is monocular). Encoder:
  4 stride-2 convolutions; decoder: 4 levels of x2 nearest up-sampling + convolution,
  concatenation with the encoder map of the same resolution, and a second convolution.
  Each of the last `num_scales` decoder levels has a sigmoid head whose output is
  mapped to inverse depth in [1 / max_depth, 1 / min_depth] (monodepth2's
  `disp_to_depth`), giving the multi-scale predictions the loss uses.
* Pose network: a stride-2 conv encoder on the pair, a 1x1 convolution to 6 numbers
  per location, averaged over the image and scaled by 0.01 (monodepth2's PoseCNN):
  axis-angle rotation and translation of camera 1 -> camera 2 (X2 = R X1 + t).

With `use_flow` (the paper's "Struct2Depth + Flow" row; `SelfSupervisedFlow`) the
optical flow, as fractions of the image size, is an extra input of both networks
(5 channels into the depth network, 8 into the pose network).

Training: the networks start from scratch, so the pose is learnt from the pairs alone;
Adam at monodepth2's 1e-4 is stable on gld_scenes. At 3e-4 the pose could overshoot
until every pixel left the view, where the loss has no gradient left (the loss term
'out_of_view_fraction' then goes to 1); watch it when changing the learning rate.

Struct2Depth's object-motion model is left out: gld_scenes and the DeMoN scenes are
static, so the rigid warp through depth and camera pose explains every pixel that the
auto-mask does not exclude.

Scale. Photometric losses fix depth only up to a common scale with the translation.
The depth network's own units are kept in 'inv_depth_scales' and 'translation' (the
loss reads these); 'depth' and 'inv_depth' are in units of the predicted baseline,
depth / ||t_predicted||, which is the convention gld evaluates in (the true ||t|| = 1),
so the evaluation needs no change and no median scaling. The pose's translation
direction is free of the scale ambiguity; its length only sets the depth unit.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import ClassVar

import flax.linen as nn
import jax
import jax.numpy as jnp

from gld.models import layers
from gld.models.baselines.small_encdec import encode, upsample_to

# Translation norms below this are treated as this (a pose net whose output is exactly
# zero); keeps 'depth' finite.
_MIN_TRANSLATION_NORM = 1e-6


def rotation_from_axis_angle(axis_angle: jax.Array) -> jax.Array:
    """Rodrigues' formula, differentiable at the zero rotation.

    Equals `gld.geometry.rotation_matrix`, whose gradient is undefined at zero (the norm
    of a zero vector): here sin(a)/a and (1 - cos a)/a^2 take their Taylor series for
    small angles, so a pose network initialised at identity still trains.

    Args:
      axis_angle: [..., 3] radians, the rotation axis times the angle.

    Returns:
      [..., 3, 3] rotation matrices.
    """
    squared_angle = jnp.sum(axis_angle**2, axis=-1)
    small = squared_angle < 1e-8
    safe_squared = jnp.where(small, 1.0, squared_angle)
    angle = jnp.sqrt(safe_squared)
    sine_term = jnp.where(small, 1.0 - squared_angle / 6.0, jnp.sin(angle) / angle)
    # (1 - cos a) / a^2 written as 2 sin^2(a / 2) / a^2: no cancellation in float32.
    half_sine_term = jnp.sin(angle / 2) / angle
    cosine_term = jnp.where(small, 0.5 - squared_angle / 24.0, 2.0 * half_sine_term**2)
    x, y, z = axis_angle[..., 0], axis_angle[..., 1], axis_angle[..., 2]
    zero = jnp.zeros_like(x)
    cross = jnp.stack(
        [
            jnp.stack([zero, -z, y], -1),
            jnp.stack([z, zero, -x], -1),
            jnp.stack([-y, x, zero], -1),
        ],
        -2,
    )
    eye = jnp.broadcast_to(jnp.eye(3, dtype=axis_angle.dtype), cross.shape)
    return eye + sine_term[..., None, None] * cross + cosine_term[..., None, None] * (cross @ cross)


class DepthNet(nn.Module):
    """U-Net from one image (+ flow) to multi-scale inverse depth.

    Attributes:
      encoder_features, encoder_kernels: the stride-2 encoder convolutions.
      decoder_features: channels of the decoder levels, coarsest first (one per encoder
        level; the last is at full resolution).
      num_scales: how many of the finest decoder levels predict inverse depth.
      min_depth, max_depth: the range the sigmoid output is mapped to.
    """

    encoder_features: Sequence[int] = (16, 32, 64, 128)
    encoder_kernels: Sequence[int] = (7, 5, 3, 3)
    decoder_features: Sequence[int] = (64, 32, 16, 16)
    num_scales: int = 4
    min_depth: float = 0.1
    max_depth: float = 100.0

    @nn.compact
    def __call__(self, inputs: jax.Array) -> tuple[jax.Array, ...]:
        """Args: inputs [B, H, W, C]. Returns inverse depth per scale, finest first:
        [B, h_s, w_s] with h_0 = H and h_s the encoder's size at 1/2^s (ceil-halved)."""
        if len(self.encoder_features) != len(self.decoder_features):
            raise ValueError(
                f"encoder and decoder need the same depth for the skips, got "
                f"{len(self.encoder_features)} and {len(self.decoder_features)} levels"
            )
        if not 1 <= self.num_scales <= len(self.decoder_features):
            raise ValueError(
                f"num_scales must be in [1, {len(self.decoder_features)}], got {self.num_scales}"
            )
        if not 0 < self.min_depth < self.max_depth:
            raise ValueError(
                f"need 0 < min_depth < max_depth, got {self.min_depth} and {self.max_depth}"
            )
        features, skips = encode(inputs, self.encoder_features, self.encoder_kernels)

        min_inv_depth, max_inv_depth = 1.0 / self.max_depth, 1.0 / self.min_depth
        first_head = len(self.decoder_features) - self.num_scales
        inv_depths = []
        for index, channels in enumerate(self.decoder_features):
            skip = skips.pop()
            features = layers.Conv(channels, (3, 3), name=f"upconv{index + 1}")(features)
            features = layers.leaky_relu(features)
            features = upsample_to(features, skip)
            features = jnp.concatenate([features, skip], axis=-1)
            features = layers.Conv(channels, (3, 3), name=f"iconv{index + 1}")(features)
            features = layers.leaky_relu(features)
            if index >= first_head:
                logits = layers.Conv(1, (3, 3), name=f"inv_depth{index + 1}")(features)[..., 0]
                sigmoid = jax.nn.sigmoid(logits)
                inv_depths.append(min_inv_depth + (max_inv_depth - min_inv_depth) * sigmoid)
        return tuple(reversed(inv_depths))


class PoseNet(nn.Module):
    """Conv encoder from the pair (+ flow) to the relative pose camera 1 -> camera 2.

    Attributes:
      features, kernels: the stride-2 convolutions.
      output_scale: factor on the 6 outputs (monodepth2: 0.01), so that the initial pose
        is close to identity.
    """

    features: Sequence[int] = (16, 32, 64, 64, 128)
    kernels: Sequence[int] = (7, 5, 3, 3, 3)
    output_scale: float = 0.01

    @nn.compact
    def __call__(self, inputs: jax.Array) -> tuple[jax.Array, jax.Array]:
        """Args: inputs [B, H, W, C]. Returns axis-angle [B, 3] (radians) and
        translation [B, 3]."""
        features = inputs
        for index, (channels, kernel) in enumerate(zip(self.features, self.kernels, strict=True)):
            features = layers.Conv(
                channels, (kernel, kernel), strides=2, padding="SAME", name=f"conv{index + 1}"
            )(features)
            features = layers.leaky_relu(features)
        pose = layers.Conv(6, (1, 1), name="pose")(features)
        pose = self.output_scale * jnp.mean(pose, axis=(1, 2))
        return pose[:, :3], pose[:, 3:]


class SelfSupervised(nn.Module):
    """Depth + pose networks trained by photometric consistency (Struct2Depth baseline).

    Attributes:
      use_flow: the flow is an extra input of both networks ("Struct2Depth + Flow").
      num_scales: scales of inverse depth the loss sees (1 to 4).
      min_depth, max_depth: range of the depth network, in its own (arbitrary) units.
      pose_scale: factor on the pose network's outputs.
    """

    # The trainer selects `gld.losses.photometric.self_supervised_loss` for this model.
    LOSS: ClassVar[str] = "self_supervised"

    use_flow: bool = False
    num_scales: int = 4
    min_depth: float = 0.1
    max_depth: float = 100.0
    pose_scale: float = 0.01

    @nn.compact
    def __call__(
        self, image1: jax.Array, image2: jax.Array, flow: jax.Array, *, train: bool = False
    ) -> dict[str, jax.Array]:
        """Predicts view-1 depth and the relative pose.

        Args:
          image1, image2: [B, H, W, 3] float32 in [-0.5, 0.5].
          flow: [B, H, W, 2] pixels, I1 -> I2 (read only with `use_flow`).
          train: unused (no dropout or normalisation).

        Returns:
          'inv_depth', 'depth': [B, H, W] in units of the predicted baseline (the
            network's depth divided by ||translation||);
          'inv_depth_scales': tuple of [B, h_s, w_s] inverse depth in the network's own
            units (those of 'translation'), full resolution first;
          'rotation': [B, 3, 3] and 'axis_angle': [B, 3], camera 1 -> camera 2;
          'translation': [B, 3] in the network's units (X2 = R X1 + t).
        """
        del train
        layers.check_inputs(image1, image2, flow)
        flow_input = [layers.normalise_flow(flow)] if self.use_flow else []
        depth_input = jnp.concatenate([image1, *flow_input], axis=-1)
        pose_input = jnp.concatenate([image1, image2, *flow_input], axis=-1)
        inv_depth_scales = DepthNet(
            num_scales=self.num_scales,
            min_depth=self.min_depth,
            max_depth=self.max_depth,
            name="depth_net",
        )(depth_input)
        axis_angle, translation = PoseNet(output_scale=self.pose_scale, name="pose_net")(pose_input)
        # The floor goes inside the root: the norm's gradient is undefined at zero.
        baseline = jnp.sqrt(jnp.maximum(jnp.sum(translation**2, axis=-1), _MIN_TRANSLATION_NORM**2))
        inv_depth = inv_depth_scales[0] * baseline[:, None, None]
        return {
            "inv_depth": inv_depth,
            "depth": 1.0 / inv_depth,
            "inv_depth_scales": inv_depth_scales,
            "rotation": rotation_from_axis_angle(axis_angle),
            "axis_angle": axis_angle,
            "translation": translation,
        }


class SelfSupervisedFlow(SelfSupervised):
    """`SelfSupervised` with the flow as an extra input of both networks: the paper's
    "Struct2Depth + Flow" row, as a class of its own so that a registry name selects it."""

    use_flow: bool = True
