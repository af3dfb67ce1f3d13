"""The objects in a room: boxes, spheres and cylinders, where rays meet them, their normals."""

from __future__ import annotations

import dataclasses

import numpy as np

from . import textures
from .vector_math import safe_reciprocal, transform

_NEAR = 1e-3  # metres; ignores self-hits of a ray leaving a surface


@dataclasses.dataclass(frozen=True)
class SceneObject:
    """A box, sphere or cylinder.

    `rotation` [3, 3] maps object-local to world directions (its columns are the
    local axes), `center` [3] is in world metres. `size` is the half extents [3]
    of a box, `[radius]` of a sphere and `[radius, half_height]` of a cylinder
    (axis along local y).
    """

    shape: str
    center: np.ndarray
    rotation: np.ndarray
    size: np.ndarray
    material: textures.Material

    @property
    def bounding_radius(self) -> float:
        if self.shape == "box":
            return float(np.linalg.norm(self.size))
        if self.shape == "sphere":
            return float(self.size[0])
        return float(np.hypot(self.size[0], self.size[1]))

    def intersect(self, origin: np.ndarray, directions: np.ndarray) -> np.ndarray:
        """Distance along each ray [N] to the first hit (inf on a miss).

        Args:
          origin: [3] world ray origin (outside the object).
          directions: [N, 3] world ray directions (any length; distances are in
            units of the direction's length).
        """
        local_origin = (origin - self.center) @ self.rotation
        local_dirs = transform(directions, self.rotation)
        if self.shape == "box":
            return _intersect_box(local_origin, local_dirs, self.size)
        if self.shape == "sphere":
            return _intersect_sphere(local_origin, local_dirs, self.size[0])
        return _intersect_cylinder(local_origin, local_dirs, self.size[0], self.size[1])

    def normals(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """World unit normals [N, 3] and object-local points [N, 3] at surface points [N, 3]."""
        local = transform(points - self.center, self.rotation)
        if self.shape == "sphere":
            local_normals = local
        elif self.shape == "box":
            axis = np.argmax(np.abs(local) / self.size, axis=-1)
            local_normals = np.zeros_like(local)
            rows = np.arange(len(local))
            local_normals[rows, axis] = np.sign(local[rows, axis])
        else:
            radius, half_height = self.size
            on_cap = np.abs(local[:, 1]) >= half_height * (1.0 - 1e-4)
            radial = local * np.array([1.0, 0.0, 1.0], np.float32)
            cap = np.zeros_like(local)
            cap[:, 1] = np.sign(local[:, 1])
            local_normals = np.where(on_cap[:, None], cap, radial)
        local_normals = local_normals / np.maximum(
            np.linalg.norm(local_normals, axis=-1, keepdims=True), 1e-12
        )
        return transform(local_normals, self.rotation.T), local


def _intersect_box(origin: np.ndarray, dirs: np.ndarray, half: np.ndarray) -> np.ndarray:
    # Slab test, one axis at a time (reductions over a length-3 axis are slow in numpy).
    t_enter, t_exit = None, None
    for axis in range(3):
        inverse = safe_reciprocal(dirs[:, axis])
        near = (-half[axis] - origin[axis]) * inverse
        far = (half[axis] - origin[axis]) * inverse
        axis_enter, axis_exit = np.minimum(near, far), np.maximum(near, far)
        if t_enter is None:
            t_enter, t_exit = axis_enter, axis_exit
        else:
            t_enter, t_exit = np.maximum(t_enter, axis_enter), np.minimum(t_exit, axis_exit)
    hit = (t_exit >= t_enter) & (t_enter > _NEAR)
    return np.where(hit, t_enter, np.inf)


def _intersect_sphere(origin: np.ndarray, dirs: np.ndarray, radius: float) -> np.ndarray:
    a = np.einsum("nj,nj->n", dirs, dirs)
    b = transform(dirs, origin)
    c = float(origin @ origin) - radius * radius
    discriminant = b * b - a * c
    t = (-b - np.sqrt(np.maximum(discriminant, 0.0))) / a
    return np.where((discriminant >= 0) & (t > _NEAR), t, np.inf)


def _intersect_cylinder(
    origin: np.ndarray, dirs: np.ndarray, radius: float, half_height: float
) -> np.ndarray:
    dx, dy, dz = dirs[:, 0], dirs[:, 1], dirs[:, 2]
    ox, oy, oz = origin
    a = dx * dx + dz * dz
    b = ox * dx + oz * dz
    c = ox * ox + oz * oz - radius * radius
    discriminant = b * b - a * c
    t_side = (-b - np.sqrt(np.maximum(discriminant, 0.0))) / np.maximum(a, 1e-12)
    side_hit = (
        (discriminant >= 0)
        & (a > 1e-12)
        & (t_side > _NEAR)
        & (np.abs(oy + t_side * dy) <= half_height)
    )
    t = np.where(side_hit, t_side, np.inf)
    if abs(oy) > half_height:  # the origin sees one cap, the one on its side
        cap_y = half_height if oy > 0 else -half_height
        t_cap = (cap_y - oy) * safe_reciprocal(dy)
        cap_x = ox + t_cap * dx
        cap_z = oz + t_cap * dz
        cap_hit = (t_cap > _NEAR) & (cap_x * cap_x + cap_z * cap_z <= radius * radius)
        t = np.where(cap_hit, np.minimum(t, t_cap), t)
    return t
