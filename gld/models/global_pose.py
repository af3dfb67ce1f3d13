"""Six global parameters as a relative camera pose, and back: how a given pose becomes
the global-local model's g (`pose_parameters`), and the pose a loss reads from g
(`global_params_pose`)."""

from __future__ import annotations

import jax
import jax.numpy as jnp

from gld import geometry

# Factor on the rotation's vector part in the given-pose global parameters: rotations of
# a few degrees (sin 3.65 deg ~ 0.064) then vary on the scale of the unit translation.
POSE_ROTATION_SCALE = 10.0


def global_params_pose(global_params: jax.Array) -> dict[str, jax.Array]:
    """The relative pose six global parameters stand for, read as `pose_parameters`
    writes it (to first order in the angle): {"rotation": [B, 3, 3] (Rodrigues of the
    first three over `POSE_ROTATION_SCALE`), "translation": [B, 3] (the last three, any
    norm)}. A loss on this pose (`gld.losses.supervised.epipolar_term`) makes g encode the
    motion."""
    if global_params.ndim != 2 or global_params.shape[1] != 6:
        raise ValueError(f"global_params must be [B, 6], got shape {global_params.shape}")
    rotation = geometry.rotation_matrix(global_params[:, :3] / POSE_ROTATION_SCALE)
    return {"rotation": rotation, "translation": global_params[:, 3:]}


def pose_parameters(rotation: jax.Array, translation: jax.Array) -> jax.Array:
    """The relative pose as six global parameters ([B, 6]): the rotation's vector part
    (sin of the angle times the axis, from the skew-symmetric part of R) times
    `POSE_ROTATION_SCALE`, then the translation's direction.

    Args:
      rotation: [B, 3, 3], X2 = R X1 + t.
      translation: [B, 3] (any norm; the contract's has norm 1).
    """
    if rotation.ndim != 3 or rotation.shape[1:] != (3, 3):
        raise ValueError(f"rotation must be [B, 3, 3], got shape {rotation.shape}")
    if translation.ndim != 2 or translation.shape[1] != 3:
        raise ValueError(f"translation must be [B, 3], got shape {translation.shape}")
    vector_part = 0.5 * jnp.stack(
        [
            rotation[:, 2, 1] - rotation[:, 1, 2],
            rotation[:, 0, 2] - rotation[:, 2, 0],
            rotation[:, 1, 0] - rotation[:, 0, 1],
        ],
        axis=-1,
    )
    return jnp.concatenate([POSE_ROTATION_SCALE * vector_part, _unit(translation)], axis=-1)


def _unit(vectors: jax.Array) -> jax.Array:
    """Vectors [..., 3] scaled to norm 1 (zero stays zero)."""
    return vectors / jnp.maximum(jnp.linalg.norm(vectors, axis=-1, keepdims=True), 1e-12)
