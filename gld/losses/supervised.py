"""The paper's training loss: sparse L1 on inverse depth + edge-aware smoothness, and an
optional epipolar term that asks the global parameters to encode the camera motion."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp

from gld import geometry
from gld.models import global_pose


@dataclasses.dataclass(frozen=True)
class LossWeights:
    """Weights of the loss terms (the paper's lambda_p and lambda_s; the epipolar term is
    not the paper's and is off by default)."""

    depth: float = 5.0
    smoothness: float = 2.0
    epipolar: float = 0.0
    pose_teacher: float = 0.0


def inverse_depth_target(depth: jax.Array, mask: jax.Array) -> jax.Array:
    """1 / depth where `mask`, 0 elsewhere ([B, H, W]); never divides by zero."""
    return jnp.where(mask, 1.0 / jnp.where(mask, depth, 1.0), 0.0)


def sparse_l1(inv_depth: jax.Array, inv_depth_true: jax.Array, mask: jax.Array) -> jax.Array:
    """Mean |z_hat - z| over the supervised pixels of the whole batch.

    Args:
      inv_depth, inv_depth_true: [B, H, W].
      mask: [B, H, W] bool, the supervised pixels (the paper's set P).

    Returns:
      Scalar; 0 when no pixel is supervised.
    """
    mask = mask.astype(inv_depth.dtype)
    total = jnp.sum(jnp.abs(inv_depth - inv_depth_true) * mask)
    return total / jnp.maximum(jnp.sum(mask), 1.0)


def edge_aware_smoothness(inv_depth: jax.Array, image: jax.Array) -> jax.Array:
    """Mean over the image of |d_x z| exp(-|d_x I|) + |d_y z| exp(-|d_y I|).

    Args:
      inv_depth: [B, H, W] predicted inverse depth.
      image: [B, H, W, C] the first image; its gradient magnitude is averaged over channels.

    Returns:
      Scalar.
    """
    weight_x = jnp.exp(-jnp.mean(jnp.abs(jnp.diff(image, axis=2)), axis=-1))
    weight_y = jnp.exp(-jnp.mean(jnp.abs(jnp.diff(image, axis=1)), axis=-1))
    smooth_x = jnp.mean(jnp.abs(jnp.diff(inv_depth, axis=2)) * weight_x)
    smooth_y = jnp.mean(jnp.abs(jnp.diff(inv_depth, axis=1)) * weight_y)
    return smooth_x + smooth_y


def epipolar_term(outputs: dict, batch: dict) -> jax.Array:
    """Mean epipolar distance (pixels) of the input flow under the pose the model's global
    parameters stand for (`outputs["global_pose"]`, `gld.geometry.epipolar_distance`).

    It needs no label: the flow the model is given and the cameras' intrinsics say which
    motions are consistent with the pair, so this term trains the global module to
    encode the motion (rotation and translation direction; not the translation's sign
    or scale), which the local network needs to turn flow into depth.
    """
    if "global_pose" not in outputs:
        raise ValueError(
            "the epipolar loss needs a model whose six global parameters stand for a pose "
            "(global_local with its global module and global_dim 6)"
        )
    # With a refined g, the term trains what the encoder proposed.
    pose = outputs.get("encoder_pose", outputs["global_pose"])
    distance = geometry.epipolar_distance(
        batch["flow"],
        pose["rotation"],
        pose["translation"],
        batch["intrinsics1"],
        batch["intrinsics2"],
    )
    return jnp.mean(distance)


def pose_teacher_term(outputs: dict, batch: dict) -> jax.Array:
    """Mean squared distance of the global parameters from the pose the essential matrix
    gets from the input flow (`gld.flow_pose`, the contract's "flow_rotation" and
    "flow_translation"), written as global parameters (`gld.models.global_local.pose_parameters`):
    a classical teacher for the global module, no label needed. Pairs whose estimate
    failed (zero translation) are left out.
    """
    if "global_pose" not in outputs:
        raise ValueError(
            "the pose-teacher loss needs a model whose six global parameters stand for a "
            "pose (global_local with its global module and global_dim 6)"
        )
    target = global_pose.pose_parameters(batch["flow_rotation"], batch["flow_translation"])
    valid = (jnp.linalg.norm(batch["flow_translation"], axis=-1) > 0.5).astype(target.dtype)
    params = outputs.get("encoder_params", outputs["global_params"])
    squared = jnp.sum((params - jax.lax.stop_gradient(target)) ** 2, axis=-1)
    return jnp.sum(squared * valid) / jnp.maximum(jnp.sum(valid), 1.0)


def total_loss(
    outputs: dict[str, jax.Array],
    batch: dict[str, jax.Array],
    weights: LossWeights = LossWeights(),
) -> tuple[jax.Array, dict[str, jax.Array]]:
    """The weighted training loss of a batch.

    Multi-scale models (DispNet-style) add `inv_depth_pyramid`: coarser predictions that
    are upsampled bilinearly to full resolution and get the same loss; the terms are
    averaged over scales so the loss keeps the single-scale magnitude.

    Args:
      outputs: the model's outputs, with `inv_depth` [B, H, W].
      batch: the example contract (`depth`, `sparse_mask`, `image1` are used; `flow`,
        `intrinsics1`, `intrinsics2` too with the epipolar term; `flow_rotation`,
        `flow_translation` with the pose teacher).
      weights: the loss weights.

    Returns:
      (loss, {"loss", "depth_l1", "smoothness"} and "epipolar", "pose_teacher" when
      weighted) where the
      terms are unweighted.
    """
    image = batch["image1"]
    mask = batch["sparse_mask"]
    inv_depth_true = inverse_depth_target(batch["depth"], mask)
    predictions = [outputs["inv_depth"]]
    full_shape = outputs["inv_depth"].shape
    for coarse in outputs.get("inv_depth_pyramid", ()):
        predictions.append(jax.image.resize(coarse, full_shape, method="bilinear"))
    depth_term = sum(sparse_l1(p, inv_depth_true, mask) for p in predictions) / len(predictions)
    smooth_term = sum(edge_aware_smoothness(p, image) for p in predictions) / len(predictions)
    loss = weights.depth * depth_term + weights.smoothness * smooth_term
    terms = {"depth_l1": depth_term, "smoothness": smooth_term}
    if weights.epipolar > 0:
        terms["epipolar"] = epipolar_term(outputs, batch)
        loss = loss + weights.epipolar * terms["epipolar"]
    if weights.pose_teacher > 0:
        terms["pose_teacher"] = pose_teacher_term(outputs, batch)
        loss = loss + weights.pose_teacher * terms["pose_teacher"]
    return loss, {"loss": loss, **terms}
