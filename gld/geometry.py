"""Pinhole two-view geometry: projection, depth -> flow, relative pose, triangulation.

Conventions (shared by every dataset, the input pipeline and the baselines):

* Pixel (u, v): u to the right, v down, (0, 0) the centre of the top-left pixel.
* Normalised intrinsics `[fx/W, fy/H, cx/W, cy/H]` refer to continuous image
  coordinates whose origin is the top-left *corner*; in pixel-index coordinates
  the principal point is therefore `(cx/W * W - 0.5, cy/H * H - 0.5)`. This
  makes normalised intrinsics independent of the resolution, and a 180 degree
  rotation or an x-mirror maps `cx/W` to `1 - cx/W` exactly.
* Poses: `X2 = R @ X1 + t` maps camera-1 coordinates to camera-2 coordinates.
* Depth is camera-z depth; 0 (or any non-positive / non-finite value) is invalid.

Every function accepts numpy or JAX arrays and returns the same kind, so the
same code serves the numpy data builders and the jitted baselines.
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

Array = Any  # np.ndarray | jax.Array


def _xp(*arrays: Array):
    """The array module (numpy or jax.numpy) matching the inputs."""
    return jnp if any(isinstance(a, jax.Array) for a in arrays) else np


def _times(matrix: Array, vectors: Array, xp) -> Array:
    """`matrix @ v` for each 3-vector v of `vectors` [..., H, W, 3]; matrix [..., 3, 3]
    (its leading axes broadcast against the vectors').

    Under JAX the product is written out as multiply-adds, which XLA fuses with what
    surrounds them: on the CPU it runs a contraction over three terms as a separate
    library call, several times slower. Under numpy, float32 operands take the same
    multiply-adds, which give numpy's float32 einsum's bits (its three products summed
    in order, no fused multiply-add) in half its time; other dtypes keep the einsum
    (float64's differs from the multiply-adds in the last bit), so what numpy computes
    (the rendered datasets' records, the classical baselines) keeps its bits."""
    if xp is np:
        matrix, vectors = np.asarray(matrix), np.asarray(vectors)
        if not matrix.dtype == vectors.dtype == np.float32:
            return np.einsum("...ij,...hwj->...hwi", matrix, vectors)
    columns = matrix[..., None, None, :, :]
    # sum() starts from 0, as numpy's einsum does (three products of -0.0 give +0.0).
    return sum(columns[..., column] * vectors[..., column : column + 1] for column in range(3))


def intrinsics_matrix(intrinsics: Array, height: int, width: int) -> Array:
    """Normalised intrinsics -> pixel-index camera matrix.

    Args:
      intrinsics: [..., 4] normalised `[fx/W, fy/H, cx/W, cy/H]`.
      height, width: image size in pixels.

    Returns:
      [..., 3, 3] K such that `K @ X` gives homogeneous pixel-index coordinates.
    """
    xp = _xp(intrinsics)
    fx = intrinsics[..., 0] * width
    fy = intrinsics[..., 1] * height
    cx = intrinsics[..., 2] * width - 0.5
    cy = intrinsics[..., 3] * height - 0.5
    zero, one = xp.zeros_like(fx), xp.ones_like(fx)
    rows = [
        xp.stack([fx, zero, cx], axis=-1),
        xp.stack([zero, fy, cy], axis=-1),
        xp.stack([zero, zero, one], axis=-1),
    ]
    return xp.stack(rows, axis=-2)


def normalised_intrinsics(camera_matrix: Array, height: int, width: int) -> Array:
    """Pixel-index camera matrix [..., 3, 3] -> normalised intrinsics [..., 4] (skew dropped)."""
    xp = _xp(camera_matrix)
    return xp.stack(
        [
            camera_matrix[..., 0, 0] / width,
            camera_matrix[..., 1, 1] / height,
            (camera_matrix[..., 0, 2] + 0.5) / width,
            (camera_matrix[..., 1, 2] + 0.5) / height,
        ],
        axis=-1,
    )


def pixel_grid(height: int, width: int, xp=np) -> Array:
    """[H, W, 2] float32 pixel-index coordinates (u, v)."""
    v, u = xp.meshgrid(
        xp.arange(height, dtype=xp.float32), xp.arange(width, dtype=xp.float32), indexing="ij"
    )
    return xp.stack([u, v], axis=-1)


def normalised_coordinates(height: int, width: int, xp=np) -> Array:
    """[H, W, 2] float32 (x, y) in [-1, 1], the CoordConv channels."""
    y, x = xp.meshgrid(
        xp.linspace(-1.0, 1.0, height, dtype=xp.float32),
        xp.linspace(-1.0, 1.0, width, dtype=xp.float32),
        indexing="ij",
    )
    return xp.stack([x, y], axis=-1)


def valid_depth(depth: Array) -> Array:
    """Boolean mask of finite, strictly positive depth."""
    xp = _xp(depth)
    return xp.isfinite(depth) & (depth > 0)


def backproject(depth: Array, camera_matrix: Array) -> Array:
    """Lifts every pixel to 3-D in its camera's frame.

    Args:
      depth: [..., H, W] camera-z depth.
      camera_matrix: [..., 3, 3] pixel-index K.

    Returns:
      [..., H, W, 3] points `depth * K^-1 [u, v, 1]`.
    """
    xp = _xp(depth, camera_matrix)
    height, width = depth.shape[-2:]
    grid = pixel_grid(height, width, xp)
    homogeneous = xp.concatenate([grid, xp.ones_like(grid[..., :1])], axis=-1)
    rays = _times(xp.linalg.inv(camera_matrix), homogeneous, xp)
    return rays * depth[..., None]


def project(points: Array, camera_matrix: Array) -> tuple[Array, Array]:
    """Projects camera-frame points.

    Args:
      points: [..., H, W, 3] in the camera's frame.
      camera_matrix: [..., 3, 3].

    Returns:
      pixels [..., H, W, 2] (u, v) and z [..., H, W]; pixels are meaningless where z <= 0.
    """
    xp = _xp(points, camera_matrix)
    image_points = _times(camera_matrix, points, xp)
    z = image_points[..., 2]
    safe_z = xp.where(xp.abs(z) > 1e-12, z, 1e-12)
    return image_points[..., :2] / safe_z[..., None], z


def transform_points(points: Array, rotation: Array, translation: Array) -> Array:
    """`R @ X + t` for points [..., H, W, 3], rotation [..., 3, 3], translation [..., 3]."""
    xp = _xp(points, rotation, translation)
    return _times(rotation, points, xp) + translation[..., None, None, :]


def depth_to_flow(
    depth: Array,
    camera_matrix1: Array,
    camera_matrix2: Array,
    rotation: Array,
    translation: Array,
) -> tuple[Array, Array]:
    """Rigid-scene flow I1 -> I2 from view-1 depth and the relative pose.

    Args:
      depth: [..., H, W] view-1 camera-z depth.
      camera_matrix1, camera_matrix2: [..., 3, 3] pixel-index K of each view.
      rotation, translation: [..., 3, 3], [..., 3]; X2 = R X1 + t.

    Returns:
      flow [..., H, W, 2] in pixels and the view-2 depth of each view-1 pixel [..., H, W]
      (the point is in front of camera 2 where it is > 0).
    """
    xp = _xp(depth, camera_matrix1, camera_matrix2, rotation, translation)
    points2 = transform_points(backproject(depth, camera_matrix1), rotation, translation)
    pixels2, z2 = project(points2, camera_matrix2)
    height, width = depth.shape[-2:]
    return pixels2 - pixel_grid(height, width, xp), z2


def rotation_flow(
    rotation: Array, camera_matrix1: Array, camera_matrix2: Array, height: int, width: int
) -> Array:
    """The flow a rotation alone gives (the flow of points at infinity), I1 -> I2.

    A rigid scene's flow is this plus the parallax, which lies along the epipolar lines
    and scales with inverse depth; the flow less this (`flow - rotation_flow(...)`) is
    the parallax alone.

    Args:
      rotation: [..., 3, 3], X2 = R X1 + t.
      camera_matrix1, camera_matrix2: [..., 3, 3] pixel-index K of each view.
      height, width: image size in pixels.

    Returns:
      [..., H, W, 2] pixels (a point that the rotation takes behind camera 2 is mapped
      through a depth clamped at 1e-6).
    """
    xp = _xp(rotation, camera_matrix1, camera_matrix2)
    homography = camera_matrix2 @ rotation @ xp.linalg.inv(camera_matrix1)
    pixels = pixel_grid(height, width, xp)
    homogeneous = xp.concatenate([pixels, xp.ones_like(pixels[..., :1])], axis=-1)
    mapped = _times(homography, homogeneous, xp)
    depth = xp.maximum(mapped[..., 2:], 1e-6)
    return mapped[..., :2] / depth - pixels


def sample_nearest(image: Array, pixels: Array) -> tuple[Array, Array]:
    """Nearest-neighbour lookup of `image` [H, W, ...] at `pixels` [H, W, 2] (numpy).

    Returns the sampled values and a mask of lookups that fell inside the image.
    """
    height, width = image.shape[:2]
    u = np.rint(pixels[..., 0])
    v = np.rint(pixels[..., 1])
    inside = np.isfinite(u) & np.isfinite(v) & (u >= 0) & (u < width) & (v >= 0) & (v < height)
    ui = np.where(inside, u, 0).astype(np.int64)
    vi = np.where(inside, v, 0).astype(np.int64)
    return image[vi, ui], inside


def sample_bilinear(image: Array, pixels: Array) -> tuple[Array, Array]:
    """Bilinear lookup of `image` [H, W, C] at `pixels` [H, W, 2] (numpy, OpenCV remap).

    Returns the sampled values [H, W, C] and a mask of lookups whose four neighbours
    all lie inside the image.
    """
    import cv2

    height, width = image.shape[:2]
    map_u = pixels[..., 0].astype(np.float32)
    map_v = pixels[..., 1].astype(np.float32)
    values = cv2.remap(
        np.ascontiguousarray(image, dtype=np.float32),
        map_u,
        map_v,
        interpolation=cv2.INTER_LINEAR,
        borderMode=cv2.BORDER_REPLICATE,
    )
    if values.ndim == 2:
        values = values[..., None]
    inside = (map_u >= 0) & (map_u <= width - 1) & (map_v >= 0) & (map_v <= height - 1)
    return values, inside


def ground_truth_flow(
    depth1: np.ndarray,
    depth2: np.ndarray | None,
    intrinsics1: np.ndarray,
    intrinsics2: np.ndarray,
    rotation: np.ndarray,
    translation: np.ndarray,
    *,
    occlusion_tolerance: float = 0.02,
) -> tuple[np.ndarray, np.ndarray]:
    """Exact flow I1 -> I2 with its validity, for dataset builders (numpy).

    A pixel's flow is valid where its view-1 depth is valid, it lands inside view 2
    in front of the camera and, when `depth2` is given, it is not occluded there:
    its predicted view-2 depth agrees with `depth2` at the landing pixel within a
    relative `occlusion_tolerance`.

    Args:
      depth1, depth2: [H, W] camera-z depth of each view (depth2 may be None).
      intrinsics1, intrinsics2: [4] normalised.
      rotation, translation: [3, 3], [3].

    Returns:
      flow [H, W, 2] float32 (0 where depth1 is invalid) and valid [H, W] bool.
    """
    height, width = depth1.shape
    valid1 = valid_depth(depth1)
    safe_depth1 = np.where(valid1, depth1, 1.0).astype(np.float64)
    flow, z2 = depth_to_flow(
        safe_depth1,
        intrinsics_matrix(np.asarray(intrinsics1, np.float64), height, width),
        intrinsics_matrix(np.asarray(intrinsics2, np.float64), height, width),
        np.asarray(rotation, np.float64),
        np.asarray(translation, np.float64),
    )
    pixels2 = pixel_grid(height, width).astype(np.float64) + flow
    valid = valid1 & (z2 > 1e-6)
    if depth2 is not None:
        landed_depth, inside = sample_nearest(depth2, pixels2)
        visible = valid_depth(landed_depth) & (
            np.abs(landed_depth - z2) <= occlusion_tolerance * np.maximum(z2, 1e-6)
        )
        valid &= inside & visible
    else:
        u, v = pixels2[..., 0], pixels2[..., 1]
        valid &= (u > -0.5) & (u < width - 0.5) & (v > -0.5) & (v < height - 0.5)
    flow = np.where(valid1[..., None], flow, 0.0)
    return flow.astype(np.float32), valid


def triangulate_depth(
    flow: Array,
    camera_matrix1: Array,
    camera_matrix2: Array,
    rotation: Array,
    translation: Array,
) -> Array:
    """Per-pixel linear triangulation of view-1 depth from flow and a known pose.

    For each pixel the 3-D point is `z * K1^-1 [u, v, 1]`; its reprojection into view 2
    must equal `p + flow(p)`. The two projection equations are linear in `z` and are
    solved in the least-squares sense (the DLT restricted to the view-1 ray).

    Args:
      flow: [..., H, W, 2] pixels, I1 -> I2.
      camera_matrix1, camera_matrix2: [..., 3, 3].
      rotation, translation: [..., 3, 3], [..., 3]; X2 = R X1 + t.

    Returns:
      depth [..., H, W]; non-positive or non-finite where the pixel cannot be triangulated
      (no parallax, or behind a camera).
    """
    xp = _xp(flow, camera_matrix1, camera_matrix2, rotation, translation)
    ray, baseline = _projection_terms(flow, camera_matrix1, camera_matrix2, rotation, translation)
    denominator = (ray**2).sum(axis=-1)
    safe = xp.where(denominator > 1e-12, denominator, 1.0)
    depth = (ray * baseline).sum(axis=-1) / safe
    return xp.where(denominator > 1e-12, depth, 0.0)


def _projection_terms(flow, camera_matrix1, camera_matrix2, rotation, translation):
    """The two projection equations of each view-1 pixel's ray in view 2, `ray * z =
    baseline` ([..., H, W, 2] each): the point `z * K1^-1 [u, v, 1]` reprojects to
    `p + flow(p)` (`x2 ~ a z + b`, a: the camera-2 image of the ray's direction, b: of
    the translation); divided by z, `baseline * rho = ray` for the inverse depth rho."""
    xp = _xp(flow, camera_matrix1, camera_matrix2, rotation, translation)
    height, width = flow.shape[-3:-1]
    grid = pixel_grid(height, width, xp)
    homogeneous = xp.concatenate([grid, xp.ones_like(grid[..., :1])], axis=-1)
    rays1 = _times(xp.linalg.inv(camera_matrix1), homogeneous, xp)
    a = _times(camera_matrix2 @ rotation, rays1, xp)
    b = xp.einsum("...ij,...j->...i", camera_matrix2, translation)[..., None, None, :]
    target = grid + flow
    ray = target * a[..., 2:] - a[..., :2]
    baseline = b[..., :2] - target * b[..., 2:]
    return ray, baseline


def triangulate_inverse_depth(
    flow: Array,
    camera_matrix1: Array,
    camera_matrix2: Array,
    rotation: Array,
    translation: Array,
    damping: float = 0.0,
) -> tuple[Array, Array]:
    """Per-pixel linear triangulation of view-1 inverse depth from flow and a known pose.

    The reprojection of the view-1 ray's point at inverse depth rho is `x2 ~ a + rho b`
    (a: the camera-2 image of the ray's direction, b: of the translation), so the two
    projection equations are linear in rho; their normal equation `lhs * rho = rhs` is
    solved with `damping` (pixels squared) added to `lhs`, a ridge that pulls rho towards
    0 (a point at infinity) where the parallax says little about it, near the epipole.
    `lhs` is, to first order, the squared length of the parallax a unit of inverse depth
    makes there. Unlike depth (`triangulate_depth`), inverse depth stays finite as the
    parallax vanishes.

    Args:
      flow: [..., H, W, 2] pixels, I1 -> I2.
      camera_matrix1, camera_matrix2: [..., 3, 3].
      rotation, translation: [..., 3, 3], [..., 3]; X2 = R X1 + t (rho comes in units of
        1 / ||t||).
      damping: >= 0; 0 gives the plain least-squares solution.

    Returns:
      (inverse depth, confidence), each [..., H, W]: the inverse depth is negative where
      the flow puts the point behind camera 1; the confidence, lhs / (lhs + damping) in
      [0, 1], is how much of it the parallax decides (0 at the epipole). Both are 0 where
      the pixel has no parallax at all.
    """
    xp = _xp(flow, camera_matrix1, camera_matrix2, rotation, translation)
    ray, baseline = _projection_terms(flow, camera_matrix1, camera_matrix2, rotation, translation)
    lhs = (baseline**2).sum(axis=-1)
    damped = lhs + damping
    solvable = damped > 1e-12
    safe = xp.where(solvable, damped, 1.0)
    inverse_depth = xp.where(solvable, (ray * baseline).sum(axis=-1) / safe, 0.0)
    return inverse_depth, xp.where(solvable, lhs / safe, 0.0)


def skew(vector: Array) -> Array:
    """[..., 3] -> the cross-product matrix [..., 3, 3] ([v]x w = v x w)."""
    xp = _xp(vector)
    x, y, z = vector[..., 0], vector[..., 1], vector[..., 2]
    zero = xp.zeros_like(x)
    return xp.stack(
        [xp.stack([zero, -z, y], -1), xp.stack([z, zero, -x], -1), xp.stack([-y, x, zero], -1)],
        axis=-2,
    )


def epipolar_distance(
    flow: Array, rotation: Array, translation: Array, intrinsics1: Array, intrinsics2: Array
) -> Array:
    """How far each flow correspondence is from satisfying the pose's epipolar constraint:
    the first-order geometric (Sampson) distance, in pixels of view 1's focal length.

    With x1, x2 the normalised camera coordinates of a pixel and of where its flow
    lands, and E = [t]x R, the distance is |x2^T E x1| / sqrt((E x1)_0^2 + (E x1)_1^2
    + (E^T x2)_0^2 + (E^T x2)_1^2) times fx. It is 0 for every pixel when the flow is
    that of a rigid scene seen under the pose, is unchanged by the scale (and sign) of
    t, and is undefined for t = 0 (the pose then fixes no epipolar geometry).

    Args:
      flow: [B, H, W, 2] pixels, view 1 -> view 2.
      rotation, translation: [B, 3, 3], [B, 3]; X2 = R X1 + t.
      intrinsics1, intrinsics2: [B, 4] normalised.

    Returns:
      [B, H, W] distances.
    """
    xp = _xp(flow, rotation, translation, intrinsics1, intrinsics2)
    height, width = flow.shape[-3:-1]
    pixels1 = pixel_grid(height, width, xp)[None]
    pixels2 = pixels1 + flow

    def camera_coordinates(pixels, intrinsics):
        inverse_k = xp.linalg.inv(intrinsics_matrix(intrinsics, height, width))
        homogeneous = xp.concatenate([pixels, xp.ones_like(pixels[..., :1])], axis=-1)
        return _times(inverse_k, homogeneous, xp)

    x1 = camera_coordinates(pixels1, intrinsics1)
    x2 = camera_coordinates(pixels2, intrinsics2)
    essential = skew(translation) @ rotation
    e_x1 = _times(essential, x1, xp)
    et_x2 = _times(xp.swapaxes(essential, -1, -2), x2, xp)
    residual = xp.sum(x2 * e_x1, axis=-1)
    gradient_sq = e_x1[..., 0] ** 2 + e_x1[..., 1] ** 2 + et_x2[..., 0] ** 2 + et_x2[..., 1] ** 2
    focal = intrinsics1[:, 0, None, None] * width
    return focal * xp.abs(residual) / xp.sqrt(gradient_sq + 1e-20)


def relative_pose(
    rotation1: Array, translation1: Array, rotation2: Array, translation2: Array
) -> tuple[Array, Array]:
    """Relative motion camera 1 -> camera 2 from world-to-camera poses.

    With `X_cam_i = R_i X_world + t_i`: `R = R2 R1^T`, `t = t2 - R t1`.
    """
    xp = _xp(rotation1, translation1, rotation2, translation2)
    rotation = rotation2 @ xp.swapaxes(rotation1, -1, -2)
    translation = translation2 - xp.einsum("...ij,...j->...i", rotation, translation1)
    return rotation, translation


def rotation_angle_degrees(rotation: Array) -> Array:
    """Angle of a rotation matrix [..., 3, 3] in degrees."""
    xp = _xp(rotation)
    trace = rotation[..., 0, 0] + rotation[..., 1, 1] + rotation[..., 2, 2]
    return xp.degrees(xp.arccos(xp.clip((trace - 1.0) / 2.0, -1.0, 1.0)))


def rotation_error_degrees(rotation: Array, rotation_true: Array) -> Array:
    """Angle of `R_true^T R` in degrees, [...]."""
    xp = _xp(rotation, rotation_true)
    return rotation_angle_degrees(xp.swapaxes(rotation_true, -1, -2) @ rotation)


def translation_error_degrees(translation: Array, translation_true: Array) -> Array:
    """Angle between two translation directions [..., 3] in degrees (scale-free)."""
    xp = _xp(translation, translation_true)
    cosine = xp.sum(translation * translation_true, axis=-1) / xp.maximum(
        xp.linalg.norm(translation, axis=-1) * xp.linalg.norm(translation_true, axis=-1), 1e-12
    )
    return xp.degrees(xp.arccos(xp.clip(cosine, -1.0, 1.0)))


def rotation_matrix(axis_angle: Array) -> Array:
    """Rodrigues: axis-angle vector [..., 3] (radians) -> rotation matrix [..., 3, 3].

    Differentiable everywhere, the zero rotation included (the angle's square root is
    taken of its square plus 1e-24, which moves no angle above ~1e-12 rad)."""
    xp = _xp(axis_angle)
    angle = xp.sqrt(xp.sum(axis_angle**2, axis=-1, keepdims=True) + 1e-24)
    cross = skew(axis_angle / angle)
    angle = angle[..., None]
    eye = xp.broadcast_to(xp.eye(3, dtype=axis_angle.dtype), cross.shape)
    return eye + xp.sin(angle) * cross + (1 - xp.cos(angle)) * (cross @ cross)
