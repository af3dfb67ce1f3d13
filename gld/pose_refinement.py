"""Refines a relative pose on the flow's epipolar geometry: a few robust Gauss-Newton
steps, in JAX, inside the model.

    rotation, translation = refine_pose(flow, rotation0, translation0, intrinsics1,
                                        intrinsics2, iterations=10)

A conv encoder with global pooling learns the camera motion from the flow slowly: trained
directly on the true pose for 2,000 steps on gld_scenes/small it stays at ~1.6 deg /
20 deg, where an essential matrix from the same flow is off by 0.44 deg / 5.6 deg. The
flow fixes the motion through the epipolar constraint, which a model need not learn:
from the encoder's proposal, each step here linearises every pixel's signed Sampson
distance (`gld.geometry.epipolar_distance` without the absolute value) in five
parameters (a rotation increment, and the translation direction moved in its tangent
plane), weights the residuals robustly (Cauchy, `sigma` pixels; correspondences that
leave image 2 get no weight) and solves the damped normal equations. From a proposal
within ~2 deg / 20 deg of the truth, ten steps land within ~0.6 deg / 6 deg on the
DIS flow of gld_scenes/small.

The translation keeps its sign (the constraint does not fix it) and unit norm.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from gld import geometry

# Pixels used: every STRIDE-th row and column (768 of 128x96's 12,288 pixels at 4).
DEFAULT_STRIDE = 4
DEFAULT_SIGMA_PIXELS = 1.0
# Levenberg-Marquardt damping, relative to the mean diagonal of the normal matrix.
_DAMPING = 1e-3


def _signed_distances(flow, rotation, translation, inverse_k1, inverse_k2, focal, stride):
    """Signed Sampson distances (pixels) of one pair's subsampled correspondences, and
    whether each lands inside image 2."""
    height, width = flow.shape[:2]
    pixels1 = geometry.pixel_grid(height, width, jnp)[::stride, ::stride].reshape(-1, 2)
    pixels2 = pixels1 + flow[::stride, ::stride].reshape(-1, 2)
    inside = (
        (pixels2[:, 0] > -0.5)
        & (pixels2[:, 0] < width - 0.5)
        & (pixels2[:, 1] > -0.5)
        & (pixels2[:, 1] < height - 0.5)
    )
    ones = jnp.ones_like(pixels1[:, :1])
    x1 = jnp.concatenate([pixels1, ones], axis=-1) @ inverse_k1.T
    x2 = jnp.concatenate([pixels2, ones], axis=-1) @ inverse_k2.T
    essential = geometry.skew(translation) @ rotation
    e_x1 = x1 @ essential.T
    et_x2 = x2 @ essential
    residual = jnp.sum(x2 * e_x1, axis=-1)
    gradient_sq = e_x1[:, 0] ** 2 + e_x1[:, 1] ** 2 + et_x2[:, 0] ** 2 + et_x2[:, 1] ** 2
    return focal * residual / jnp.sqrt(gradient_sq + 1e-12), inside


def _tangent_basis(direction):
    """Two unit vectors spanning the plane perpendicular to a unit `direction` [3]."""
    helper = jnp.where(
        jnp.abs(direction[0]) < 0.9, jnp.array([1.0, 0.0, 0.0]), jnp.array([0.0, 1.0, 0.0])
    )
    first = jnp.cross(direction, helper.astype(direction.dtype))
    first = first / jnp.linalg.norm(first)
    return first, jnp.cross(direction, first)


def _moved(rotation, translation, step, basis):
    rotation = geometry.rotation_matrix(step[:3]) @ rotation
    translation = translation + step[3] * basis[0] + step[4] * basis[1]
    return rotation, translation / jnp.linalg.norm(translation)


def _refine_one(
    flow, rotation, translation, inverse_k1, inverse_k2, focal, iterations, stride, sigma
):
    translation = translation / jnp.maximum(jnp.linalg.norm(translation), 1e-12)

    def step(_, pose):
        rotation, translation = pose
        basis = _tangent_basis(translation)

        def distances(increment):
            moved = _moved(rotation, translation, increment, basis)
            return _signed_distances(flow, *moved, inverse_k1, inverse_k2, focal, stride)[0]

        residual, inside = _signed_distances(
            flow, rotation, translation, inverse_k1, inverse_k2, focal, stride
        )
        jacobian = jax.jacfwd(distances)(jnp.zeros(5, flow.dtype))
        weights = inside / (1.0 + (residual / sigma) ** 2)
        weighted = jacobian * weights[:, None]
        normal = weighted.T @ jacobian
        normal = normal + (_DAMPING * jnp.trace(normal) / 5 + 1e-9) * jnp.eye(5, dtype=flow.dtype)
        increment = -jnp.linalg.solve(normal, weighted.T @ residual)
        return _moved(rotation, translation, increment, basis)

    return jax.lax.fori_loop(0, iterations, step, (rotation, translation))


def refine_pose(
    flow: jax.Array,
    rotation: jax.Array,
    translation: jax.Array,
    intrinsics1: jax.Array,
    intrinsics2: jax.Array,
    *,
    iterations: int = 10,
    stride: int = DEFAULT_STRIDE,
    sigma: float = DEFAULT_SIGMA_PIXELS,
) -> tuple[jax.Array, jax.Array]:
    """The pose that best explains the flow's epipolar geometry near a proposal.

    Args:
      flow: [B, H, W, 2] pixels, I1 -> I2.
      rotation, translation: [B, 3, 3], [B, 3] the proposal (X2 = R X1 + t; any norm,
        not zero).
      intrinsics1, intrinsics2: [B, 4] normalised.
      iterations: Gauss-Newton steps (0 returns the proposal, translation at unit norm).
      stride: every stride-th pixel row and column is a correspondence.
      sigma: the Cauchy weight's scale, pixels.

    Returns:
      (rotation [B, 3, 3], unit translation [B, 3]), in the flow's dtype.
    """
    if flow.ndim != 4 or flow.shape[-1] != 2:
        raise ValueError(f"flow must be [B, H, W, 2], got shape {flow.shape}")
    if iterations < 0 or stride < 1 or not sigma > 0:
        raise ValueError(
            f"iterations must be >= 0, stride >= 1 and sigma > 0; got {iterations}, {stride}, "
            f"{sigma}"
        )
    dtype = flow.dtype
    height, width = flow.shape[1:3]
    inverse_k1, inverse_k2 = (
        jnp.linalg.inv(geometry.intrinsics_matrix(intrinsics.astype(dtype), height, width))
        for intrinsics in (intrinsics1, intrinsics2)
    )
    focal = intrinsics1[:, 0].astype(dtype) * width

    def one(*arguments):
        return _refine_one(*arguments, iterations, stride, sigma)

    return jax.vmap(one)(
        flow, rotation.astype(dtype), translation.astype(dtype), inverse_k1, inverse_k2, focal
    )
