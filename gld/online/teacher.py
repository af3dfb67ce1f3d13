"""Labels from the classical pipeline on a pair's own flow: a teacher the robot carries.

The range sensor labels one pixel a frame. The pair's flow says more, where it says it
well: the essential matrix's pose from the flow (`gld.flow_pose`, RANSAC and cheirality)
fixes the epipolar geometry, and a pixel whose flow moves along its epipolar line by
more than the flow's noise (its parallax: the flow less the rotation's flow) and lies on
it (a small epipolar distance) triangulates to a depth the flow decides. The error of
such labels on the simulated robot's stream, and why more parallax does not make them
better (DIS errs along the epipolar line too, where no test sees it), are measured in
WORKSPACE.md ("A classical teacher"). `classical_labels` draws up to `count` such
pixels and labels them with that depth, in the learner's units (baselines: the
essential matrix's translation has unit norm, as the odometry's baseline is the unit of
the range readings). Nothing here reads the truth; a surface nearer than `min_depth`
metres (the odometry's baseline converts) is taken for a mismatch and left out.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from gld import flow_pose, geometry


@dataclasses.dataclass(frozen=True)
class TeacherSettings:
    """Which pixels of a pair the classical pipeline labels.

    Attributes:
      count: labels drawn a pair (0: no teacher).
      min_parallax: pixels of parallax (the flow less the rotation's flow, the part the
        translation makes) a label needs; below it the depth is the flow's noise over a
        short lever.
      max_epipolar: pixels the flow may lie off its epipolar line (the RANSAC inlier
        threshold of `gld.flow_pose` is 0.5).
      min_depth: metres; a nearer triangulated surface is left out.
    """

    count: int = 0
    min_parallax: float = 1.0
    max_epipolar: float = 0.5
    min_depth: float = 0.3

    def __post_init__(self):
        if self.count < 0:
            raise ValueError(f"teacher count must be >= 0, got {self.count}")
        for name in ("min_parallax", "max_epipolar", "min_depth"):
            if not getattr(self, name) > 0:
                raise ValueError(f"teacher {name} must be > 0, got {getattr(self, name)}")


def classical_labels(
    example: dict[str, np.ndarray],
    baseline: float,
    settings: TeacherSettings,
    rng: np.random.Generator,
) -> np.ndarray:
    """[N, 3] (row, column, depth in baselines), N <= settings.count, of the pair
    `example` (the example contract's flow and intrinsics, one pair) whose odometry
    baseline is `baseline` metres; empty where the pose fails or no pixel qualifies."""
    none = np.zeros((0, 3), np.float32)
    if settings.count == 0:
        return none
    flow = np.asarray(example["flow"], np.float32)
    height, width = flow.shape[:2]
    rotation, translation, succeeded = flow_pose.pose_of_example(
        flow, example["intrinsics1"], example["intrinsics2"]
    )
    if not succeeded:
        return none
    intrinsics1 = np.asarray(example["intrinsics1"], np.float64)
    intrinsics2 = np.asarray(example["intrinsics2"], np.float64)
    camera1 = geometry.intrinsics_matrix(intrinsics1, height, width)
    camera2 = geometry.intrinsics_matrix(intrinsics2, height, width)
    flow64, rotation64 = flow.astype(np.float64), rotation.astype(np.float64)
    translation64 = translation.astype(np.float64)
    inverse_depth, _ = geometry.triangulate_inverse_depth(
        flow64, camera1, camera2, rotation64, translation64
    )
    # The flow less the rotation's: the parallax, which the translation alone makes.
    parallax = np.linalg.norm(
        flow64 - geometry.rotation_flow(rotation64, camera1, camera2, height, width), axis=-1
    )
    epipolar = geometry.epipolar_distance(
        flow64[None],
        rotation64[None],
        translation64[None],
        intrinsics1[None],
        intrinsics2[None],
    )[0]
    nearest = settings.min_depth / baseline  # the nearest accepted depth, baselines
    keep = (
        (inverse_depth > 0)
        & (parallax >= settings.min_parallax)
        & (epipolar <= settings.max_epipolar)
        & (inverse_depth <= 1.0 / nearest)
    )
    rows, columns = np.nonzero(keep)
    if len(rows) > settings.count:
        chosen = np.sort(rng.choice(len(rows), settings.count, replace=False))
        rows, columns = rows[chosen], columns[chosen]
    depth = 1.0 / inverse_depth[rows, columns]
    return np.stack([rows, columns, depth], axis=1).astype(np.float32)
