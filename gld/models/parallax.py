"""What the flow says about depth once the global parameters are read as a pose.

Six global parameters stand for a relative pose (`global_params_pose`). Given it, a
rigid scene's flow splits into the flow of the rotation (the flow of points at infinity,
`gld.geometry.rotation_flow`) and the parallax, which lies along the epipolar lines and
scales with inverse depth. `parallax_flow` is the flow less the rotation's
(`GlobalLocal.derotate_flow`); `parallax_inverse_depth` is the inverse depth each pixel's
flow gives by triangulation under that pose (`GlobalLocal.parallax_depth`).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from gld import geometry
from gld.models.global_pose import global_params_pose

# The ridge of the per-pixel triangulation, as a fraction of the image width: the
# parallax direction's length (in pixels) below which a pixel's inverse depth is pulled
# towards 0 (4 px at 128 wide).
DAMPING_WIDTH_FRACTION = 1 / 32
# The local network's inverse-depth channel: the triangulated inverse depth (in units of
# 1 / ||t||) times this, clipped to [0, INVERSE_DEPTH_CLIP], on the scale of the other
# inputs.
INVERSE_DEPTH_SCALE = 10.0
INVERSE_DEPTH_CLIP = 10.0


def _cameras(flow: jax.Array, intrinsics1: jax.Array, intrinsics2: jax.Array):
    height, width = flow.shape[1:3]
    return tuple(
        geometry.intrinsics_matrix(intrinsics.astype(flow.dtype), height, width)
        for intrinsics in (intrinsics1, intrinsics2)
    )


def parallax_flow(
    flow: jax.Array, global_params: jax.Array, intrinsics1: jax.Array, intrinsics2: jax.Array
) -> jax.Array:
    """The flow [B, H, W, 2] (pixels) less the flow of the rotation six global parameters
    stand for (`global_params_pose`), with the cameras' normalised intrinsics [B, 4]: the
    parallax alone, as `GlobalLocal.derotate_flow` gives it to the local network."""
    height, width = flow.shape[1:3]
    camera1, camera2 = _cameras(flow, intrinsics1, intrinsics2)
    rotation = global_params_pose(global_params)["rotation"]
    return flow - geometry.rotation_flow(rotation, camera1, camera2, height, width)


def parallax_inverse_depth(
    flow: jax.Array, global_params: jax.Array, intrinsics1: jax.Array, intrinsics2: jax.Array
) -> jax.Array:
    """What the flow (pixels) says about each pixel's inverse depth under the pose six
    global parameters stand for, its translation taken as a unit direction (the scale the
    model predicts in: ||t|| = 1), with the cameras' normalised intrinsics [B, 4]
    (`GlobalLocal.parallax_depth`): [B, H, W, 2], the damped linear triangulation
    (`gld.geometry.triangulate_inverse_depth`) times INVERSE_DEPTH_SCALE, clipped to
    [0, INVERSE_DEPTH_CLIP] (a point behind the camera is noise), and its confidence in
    [0, 1), how much of it the parallax decides (0 at the epipole, where the
    triangulation says "far" for want of parallax and the image must say the rest).
    g enters as a constant (no gradient): the channel is an input, not a path by which
    the depth loss moves the pose (as through the refinement)."""
    width = flow.shape[2]
    camera1, camera2 = _cameras(flow, intrinsics1, intrinsics2)
    pose = global_params_pose(jax.lax.stop_gradient(global_params))
    translation = pose["translation"]
    norm = jnp.linalg.norm(translation, axis=-1, keepdims=True)
    direction = translation / jnp.maximum(norm, 1e-12)
    inverse_depth, confidence = geometry.triangulate_inverse_depth(
        flow,
        camera1,
        camera2,
        pose["rotation"],
        direction,
        damping=(DAMPING_WIDTH_FRACTION * width) ** 2,
    )
    inverse_depth = jnp.clip(INVERSE_DEPTH_SCALE * inverse_depth, 0.0, INVERSE_DEPTH_CLIP)
    return jnp.stack([inverse_depth, confidence], axis=-1).astype(flow.dtype)
