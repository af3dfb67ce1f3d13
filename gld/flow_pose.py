"""The relative camera motion from a flow field: the classical essential-matrix pose.

    rotation, translation, succeeded = estimate_pose(flow, camera_matrix1, camera_matrix2)
    rotation, translation, succeeded = pose_of_example(flow, intrinsics1, intrinsics2)
    poses = in_parallel(estimate_pose, [(flow, camera_matrix1, camera_matrix2), ...])

Correspondences are the pixels of a regular grid (at most `max_correspondences`) and
their flow targets inside image 2. The essential matrix comes from
`cv2.findEssentialMat` (USAC_ACCURATE: RANSAC with local optimisation and a final
refinement on all inliers, from a fixed random state, so a flow field always gives the
same pose) on normalised camera coordinates, so the two views may have different
intrinsics; `recover_pose` picks R, t by cheirality, as `cv2.recoverPose` does, about
three times faster. t has unit norm. OpenCV releases Python's lock while it estimates, so
`in_parallel` runs a batch's pairs on every core (twice as fast on two).

A pair fails when it has too few correspondences, too little parallax (median flow
below `min_parallax_pixels`: the pose is then undetermined), no essential matrix, or
fewer than `min_inliers` cheirality inliers; a failed pair gets the identity rotation
and a zero translation.

The classical pipeline (`gld.models.baselines.classical.SfMFlow`) triangulates on this pose;
a global-local model with `global_source="flow_pose"` takes it as its global
parameters (`gld.models.global_local.pose_parameters`), so a robot gets the motion from its own
flow without odometry, and the learned part is only the depth.
"""

from __future__ import annotations

import concurrent.futures
import dataclasses
import hashlib
import math
import os
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from gld import geometry
from gld.flow import opencv

# The example-contract keys of the pose estimated from the input flow.
FLOW_POSE_KEYS = ("flow_rotation", "flow_translation")


@dataclasses.dataclass(frozen=True)
class PoseSettings:
    """The estimator's settings (the defaults are `SfMFlow`'s and `flow_pose`'s)."""

    ransac_threshold_pixels: float = 0.5
    confidence: float = 0.999
    max_correspondences: int = 5000
    min_inliers: int = 20
    min_parallax_pixels: float = 0.5


DEFAULT_SETTINGS = PoseSettings()


def _normalised(pixels: np.ndarray, camera_matrix: np.ndarray) -> np.ndarray:
    homogeneous = np.concatenate([pixels, np.ones_like(pixels[:, :1])], axis=-1)
    rays = homogeneous @ np.linalg.inv(camera_matrix).T
    return np.ascontiguousarray(rays[:, :2] / rays[:, 2:])


def estimate_pose(
    flow: np.ndarray,
    camera_matrix1: np.ndarray,
    camera_matrix2: np.ndarray,
    settings: PoseSettings = DEFAULT_SETTINGS,
) -> tuple[np.ndarray, np.ndarray, bool]:
    """Relative pose of one pair from its flow.

    Args:
      flow: [H, W, 2] pixels, I1 -> I2.
      camera_matrix1, camera_matrix2: [3, 3] pixel-index K.
      settings: the estimator's thresholds.

    Returns:
      rotation [3, 3] float64, unit translation [3] float64 (X2 = R X1 + t), and whether
      it succeeded (identity and zero translation when not).
    """
    failure = np.eye(3), np.zeros(3), False
    flow = np.asarray(flow)
    if flow.ndim != 3 or flow.shape[-1] != 2:
        raise ValueError(f"flow must be [H, W, 2], got shape {flow.shape}")
    height, width = flow.shape[:2]
    step = max(1, math.ceil(math.sqrt(height * width / settings.max_correspondences)))
    grid = geometry.pixel_grid(height, width)[step // 2 :: step, step // 2 :: step]
    grid_flow = np.asarray(flow, np.float64)[step // 2 :: step, step // 2 :: step]
    targets = grid + grid_flow
    usable = (
        np.all(np.isfinite(grid_flow), axis=-1)
        & (targets[..., 0] >= -0.5)
        & (targets[..., 0] <= width - 0.5)
        & (targets[..., 1] >= -0.5)
        & (targets[..., 1] <= height - 0.5)
    )
    if usable.sum() < max(settings.min_inliers, 5):
        return failure
    if np.median(np.linalg.norm(grid_flow[usable], axis=-1)) < settings.min_parallax_pixels:
        return failure
    points1 = _normalised(grid[usable].astype(np.float64), camera_matrix1)
    points2 = _normalised(targets[usable], camera_matrix2)
    mean_focal = 0.25 * (
        camera_matrix1[0, 0] + camera_matrix1[1, 1] + camera_matrix2[0, 0] + camera_matrix2[1, 1]
    )
    identity = np.eye(3)
    cv2 = opencv()
    essential, ransac_mask = cv2.findEssentialMat(
        points1,
        points2,
        identity,
        method=cv2.USAC_ACCURATE,
        prob=settings.confidence,
        threshold=settings.ransac_threshold_pixels / mean_focal,
    )
    if essential is None or essential.shape[0] < 3 or not np.all(np.isfinite(essential)):
        return failure
    inliers = ransac_mask.ravel() > 0
    if inliers.sum() < settings.min_inliers:
        return failure
    # Several solutions come stacked as [3k, 3]; take the best-supported (first).
    inlier_count, rotation, translation = recover_pose(
        essential[:3], points1[inliers], points2[inliers]
    )
    if (
        inlier_count < settings.min_inliers
        or not np.all(np.isfinite(rotation))
        or not np.all(np.isfinite(translation))
    ):
        return failure
    return rotation, translation / np.linalg.norm(translation), True


# `cv2.recoverPose`'s distance (in units of the baseline) beyond which a triangulated
# point counts as at infinity, in front of neither camera.
CHEIRALITY_DISTANCE = 50.0


def recover_pose(
    essential: np.ndarray, points1: np.ndarray, points2: np.ndarray
) -> tuple[int, np.ndarray, np.ndarray]:
    """`cv2.recoverPose(essential, points1, points2, np.eye(3))` on normalised points: the
    essential matrix's pose with the most points in front of both cameras.

    As OpenCV does, each point is triangulated (the least singular vector of its 4x4
    linear system) for the decomposition's poses (R1, t), (R2, t), (R1, -t), (R2, -t); a
    point counts for a pose when its depth in both views lies in (0,
    `CHEIRALITY_DISTANCE`); the first pose of the largest count wins. The -t poses'
    points are the t poses' with the homogeneous coordinate negated, so two systems per
    point are solved, vectorised over the points, instead of OpenCV's four SVDs each.

    Args:
      essential: [3, 3].
      points1, points2: [N, 2] float64 normalised camera coordinates.

    Returns:
      The count of the chosen pose, its rotation [3, 3] and translation [3] (OpenCV's
      decomposition's, bit for bit). The triangulations agree with OpenCV's to rounding,
      so a count differs only by a point whose depth lies within rounding of a bound: on
      gld_scenes/small's 2,200 pairs every count and pose is OpenCV's.
    """
    rotation1, rotation2, translation = opencv().decomposeEssentialMat(essential)
    translation = translation[:, 0]
    x1, y1 = points1[:, 0], points1[:, 1]
    x2, y2 = points2[:, 0], points2[:, 1]
    zero, one = np.zeros_like(x1), np.ones_like(x1)
    counts = {}
    for index, rotation in enumerate((rotation1, rotation2)):
        # DLT rows of P1 = [I | 0] and P2 = [R | t]: x * P[2] - P[0], y * P[2] - P[1].
        system = np.array(
            [
                [-one, zero, x1, zero],
                [zero, -one, y1, zero],
                [
                    *(x2 * rotation[2, k] - rotation[0, k] for k in range(3)),
                    x2 * translation[2] - translation[0],
                ],
                [
                    *(y2 * rotation[2, k] - rotation[1, k] for k in range(3)),
                    y2 * translation[2] - translation[1],
                ],
            ]
        )
        point = _least_singular_vectors(system)
        with np.errstate(divide="ignore", invalid="ignore"):
            depth1 = point[2] / point[3]
            depth2 = (rotation[2] @ point[:3]) / point[3] + translation[2]
        for sign in (1.0, -1.0):
            counts[index, sign] = int(
                np.count_nonzero(
                    (sign * depth1 > 0)
                    & (sign * depth1 < CHEIRALITY_DISTANCE)
                    & (sign * depth2 > 0)
                    & (sign * depth2 < CHEIRALITY_DISTANCE)
                )
            )
    order = [(0, 1.0), (1, 1.0), (0, -1.0), (1, -1.0)]  # OpenCV's order of the four poses
    index, sign = max(order, key=lambda pose: counts[pose])  # the first of the largest
    return counts[index, sign], (rotation1, rotation2)[index], sign * translation


def _least_singular_vectors(
    system: np.ndarray, iterations: int = 3, tolerance: float = 1e-10
) -> np.ndarray:
    """[4, 4, N] matrices A (entry [i, j] of each point) -> [4, N] unit vectors v that
    minimise |A v|: the eigenvectors of the smallest eigenvalue of M = A^T A.

    The adjugate adj(M) = det(M) M^-1 (cofactors through the 2x2 minors of M's rows 0-1
    and 2-3) weights M's eigenvectors by the inverse of their eigenvalues; its column of
    largest diagonal entry, multiplied by adj(M) `iterations` times (inverse iteration
    without a solve), converges to the least eigenvector, at the ratio of the two
    smallest eigenvalues per step. A vector that still moves by more than `tolerance` in
    a last step (an outlier whose two smallest singular values are close), or is not
    finite (an adjugate of zero), is computed by an SVD instead.
    """
    m = np.einsum("kin,kjn->ijn", system, system)

    def minor(rows: tuple[int, int], columns: tuple[int, int]) -> np.ndarray:
        (r0, r1), (c0, c1) = rows, columns
        return m[r0, c0] * m[r1, c1] - m[r0, c1] * m[r1, c0]

    column_pairs = [(0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3)]
    upper = {pair: minor((0, 1), pair) for pair in column_pairs}
    lower = {pair: minor((2, 3), pair) for pair in column_pairs}

    def cofactor(row: int, column: int) -> np.ndarray:
        # The 3x3 minor without (row, column), expanded along the other row of the row's
        # own block (first or last of the minor's rows: no sign of its own) into the
        # other block's 2x2 minors.
        block, other = ((0, 1), lower) if row < 2 else ((2, 3), upper)
        mate = block[1] if row == block[0] else block[0]
        rest = [c for c in range(4) if c != column]
        value = sum(
            (-1) ** position * m[mate, c] * other[tuple(x for x in rest if x != c)]
            for position, c in enumerate(rest)
        )
        return (-1) ** (row + column) * value

    adjugate = np.array([[cofactor(j, i) for j in range(4)] for i in range(4)])
    diagonal = np.abs(np.einsum("iin->in", adjugate))
    vectors = adjugate[:, np.argmax(diagonal, axis=0), np.arange(adjugate.shape[2])]

    def normalised(vectors: np.ndarray) -> np.ndarray:
        return vectors / np.sqrt(np.einsum("in,in->n", vectors, vectors))

    with np.errstate(divide="ignore", invalid="ignore"):
        for _ in range(iterations):
            vectors = np.einsum("ijn,jn->in", adjugate, normalised(vectors))
        vectors = normalised(vectors)
        last = normalised(np.einsum("ijn,jn->in", adjugate, vectors))
        last *= np.sign(np.einsum("in,in->n", vectors, last))
        moved = np.sqrt(np.einsum("in,in->n", vectors - last, vectors - last))
    unsettled = ~(moved <= tolerance)
    if unsettled.any():
        vectors[:, unsettled] = np.linalg.svd(np.moveaxis(system[:, :, unsettled], -1, 0))[2][
            :, -1
        ].T
    return vectors


def in_parallel(estimate: Callable[..., Any], pairs: Sequence[tuple]) -> list[Any]:
    """`estimate(*pair)` for each of `pairs`, in order, on a thread per core (at most one
    per pair): the pose estimators spend most of their time in OpenCV, outside Python's lock."""
    workers = min(len(pairs), len(os.sched_getaffinity(0)))
    if workers <= 1:
        return [estimate(*pair) for pair in pairs]
    with concurrent.futures.ThreadPoolExecutor(workers) as pool:
        return list(pool.map(lambda pair: estimate(*pair), pairs))


# Poses already estimated in this process, by a digest of the flow and intrinsics: the
# pipeline sees every training pair once per epoch, and its flow never changes.
_CACHE: dict[bytes, tuple[np.ndarray, np.ndarray, bool]] = {}
_CACHE_LIMIT = 200_000


def pose_of_example(
    flow: np.ndarray, intrinsics1: np.ndarray, intrinsics2: np.ndarray
) -> tuple[np.ndarray, np.ndarray, bool]:
    """`estimate_pose` for the example contract's fields, cached by their content.

    Args:
      flow: [H, W, 2] pixels, I1 -> I2.
      intrinsics1, intrinsics2: [4] normalised (fx/W, fy/H, cx/W, cy/H).

    Returns:
      rotation [3, 3] float32, translation [3] float32 (unit, or zero on failure),
      whether the estimate succeeded.
    """
    flow = np.ascontiguousarray(flow, np.float32)
    intrinsics1 = np.ascontiguousarray(intrinsics1, np.float32)
    intrinsics2 = np.ascontiguousarray(intrinsics2, np.float32)
    digest = hashlib.blake2b(digest_size=16)
    for value in (flow, intrinsics1, intrinsics2):
        digest.update(str(value.shape).encode())
        digest.update(value.tobytes())
    key = digest.digest()
    cached = _CACHE.get(key)
    if cached is None:
        height, width = flow.shape[:2]
        rotation, translation, succeeded = estimate_pose(
            flow,
            geometry.intrinsics_matrix(intrinsics1.astype(np.float64), height, width),
            geometry.intrinsics_matrix(intrinsics2.astype(np.float64), height, width),
        )
        cached = rotation.astype(np.float32), translation.astype(np.float32), succeeded
        if len(_CACHE) >= _CACHE_LIMIT:
            _CACHE.clear()
        _CACHE[key] = cached
    rotation, translation, succeeded = cached
    return rotation.copy(), translation.copy(), succeeded
