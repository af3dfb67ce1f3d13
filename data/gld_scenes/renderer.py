"""Procedural two-view indoor scenes with exact depth, pose, intrinsics and flow.

A vectorised numpy ray caster in the spirit of DeMoN's Scenes11: a closed room
(floor, four walls, ceiling) holding a few boxes, spheres and cylinders, coloured
by solid procedural textures (plain, checkers, stripes, gradients, value noise)
and lit by ambient light plus one point light with Lambertian shading. Colour is
a function of the 3-D point only (no specular term), so a point looks the same
from both views and image 2 warped by the true flow reproduces image 1.

Geometry follows `gld.geometry`: pixel (0, 0) is the centre of the top-left
pixel, intrinsics are normalised `[fx/W, fy/H, cx/W, cy/H]`, poses are
world-to-camera `X_cam = R X_world + t` and the relative pose is `X2 = R X1 + t`.
The world has y pointing up, the floor at y = 0. Rays are cast along
`R^T K^-1 [u, v, 1]`, whose camera-z component is 1, so the hit distance along a
ray *is* camera-z depth.

Every random choice comes from the `numpy.random.Generator` handed in, so a pair
is a pure function of its seed (see `example_rng`).
"""

from __future__ import annotations

import dataclasses
import zlib
from typing import Any

import numpy as np

from gld import geometry

# DeMoN's nominal normalised intrinsics [fx/W, fy/H, cx/W, cy/H] (256x192 images).
NOMINAL_INTRINSICS = (0.89115971, 1.18821287, 0.5, 0.5)

TEXTURES = ("plain", "checker", "stripes", "gradient", "noise")
SHAPES = ("box", "sphere", "cylinder")
# Room surfaces are ids 0..5 in the surface map; object k has id ROOM_SURFACES + k.
ROOM_SURFACES = 6
_NEAR = 1e-3  # metres; ignores self-hits of a ray leaving a surface
_NOISE_LATTICE = 8  # periodic value-noise lattice size per axis


def _transform(vectors: np.ndarray, matrix: np.ndarray) -> np.ndarray:
    """`vectors @ matrix` for [N, 3] @ [3, K] without BLAS.

    Elementwise products give bit-identical results whatever the thread count and
    array size (BLAS kernels may not), which keeps renders reproducible.
    """
    matrix = np.asarray(matrix, vectors.dtype)
    if matrix.ndim == 1:
        return vectors[:, 0] * matrix[0] + vectors[:, 1] * matrix[1] + vectors[:, 2] * matrix[2]
    return vectors[:, :1] * matrix[0] + vectors[:, 1:2] * matrix[1] + vectors[:, 2:3] * matrix[2]


@dataclasses.dataclass(frozen=True)
class SceneSettings:
    """Settings of the scene and camera-motion generator.

    Attributes:
      height, width: image size in pixels.
      intrinsics: nominal normalised intrinsics of both views.
      intrinsics_jitter: each of fx, fy, cx, cy of each view is multiplied by an
        independent factor in [1 - jitter, 1 + jitter] (0.2 for the paper's
        varying-intrinsics experiment; 0 keeps the nominal intrinsics).
      max_rotation_degrees: the relative rotation angle is uniform in [0, this].
      min_translation, max_translation: norm range of the relative translation
        (metres, uniform direction).
      max_flow_fraction: the 99th percentile of the true flow magnitude is kept
        below this fraction of the image width (40 px at 256x192) by shrinking
        the motion.
      min_objects, max_objects: number of objects drawn (inclusive); an object that
        would come too close to the first camera is dropped.
    """

    height: int = 192
    width: int = 256
    intrinsics: tuple[float, float, float, float] = NOMINAL_INTRINSICS
    intrinsics_jitter: float = 0.0
    max_rotation_degrees: float = 10.0
    min_translation: float = 0.05
    max_translation: float = 0.5
    max_flow_fraction: float = 40.0 / 256.0
    min_objects: int = 2
    max_objects: int = 8

    def __post_init__(self):
        if self.height < 8 or self.width < 8:
            raise ValueError(f"image size must be at least 8x8, got {self.height}x{self.width}")
        if not 0.0 <= self.intrinsics_jitter < 1.0:
            raise ValueError(f"intrinsics_jitter must be in [0, 1), got {self.intrinsics_jitter}")
        if not 0 < self.min_translation <= self.max_translation:
            raise ValueError(
                f"need 0 < min_translation <= max_translation, got "
                f"{self.min_translation}, {self.max_translation}"
            )
        if not 0 <= self.min_objects <= self.max_objects <= 200:
            raise ValueError(
                f"need 0 <= min_objects <= max_objects, got {self.min_objects}, {self.max_objects}"
            )


@dataclasses.dataclass(frozen=True)
class Material:
    """A solid texture: colour as a function of a 3-D point (metres).

    `kind` is one of `TEXTURES`; `color_a`/`color_b` are RGB in [0, 1]; `scale` is
    the period in metres; `direction` orients stripes and gradients; `offset`
    shifts the lattice so no surface lies on a checker boundary; `lattice` holds
    the value-noise samples.
    """

    kind: str
    color_a: np.ndarray
    color_b: np.ndarray
    scale: float
    direction: np.ndarray
    offset: np.ndarray
    lattice: np.ndarray | None = None

    def albedo(self, points: np.ndarray) -> np.ndarray:
        """RGB albedo [N, 3] at points [N, 3]."""
        if self.kind == "plain":
            return np.broadcast_to(self.color_a, points.shape).astype(np.float32)
        coords = (points + self.offset) / self.scale
        if self.kind == "checker":
            weight = (np.floor(coords).astype(np.int64).sum(-1) & 1).astype(np.float32)
        elif self.kind == "stripes":
            weight = 0.5 + 0.5 * np.sin(2.0 * np.pi * _transform(coords, self.direction))
        elif self.kind == "gradient":
            weight = np.clip(_transform(coords, self.direction), 0.0, 1.0)
        elif self.kind == "noise":
            weight = 0.65 * _value_noise(self.lattice, coords) + 0.35 * _value_noise(
                self.lattice, 2.7 * coords + 3.1
            )
        else:
            raise ValueError(f"unknown texture {self.kind!r}; valid: {TEXTURES}")
        weight = weight.astype(np.float32)[:, None]
        return self.color_a + weight * (self.color_b - self.color_a)


def _value_noise(lattice: np.ndarray, coords: np.ndarray) -> np.ndarray:
    """Smooth periodic value noise in [0, 1] at coords [N, 3] (lattice units)."""
    size = lattice.shape[0]  # a power of two, so `& (size - 1)` wraps indices
    values = lattice.ravel()
    base = np.floor(coords)
    frac = coords - base
    frac = frac * frac * (3.0 - 2.0 * frac)  # smoothstep: continuous derivative
    low = base.astype(np.int64) & (size - 1)
    high = (low + 1) & (size - 1)
    x0, x1 = low[:, 0] * size * size, high[:, 0] * size * size
    y0, y1 = low[:, 1] * size, high[:, 1] * size
    z0, z1 = low[:, 2], high[:, 2]
    fx, fy, fz = frac[:, 0], frac[:, 1], frac[:, 2]

    def lerp(a, b, t):
        return a + t * (b - a)

    def edge(x, y):
        return lerp(values[x + y + z0], values[x + y + z1], fz)

    return lerp(lerp(edge(x0, y0), edge(x0, y1), fy), lerp(edge(x1, y0), edge(x1, y1), fy), fx)


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
    material: Material

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
        local_dirs = _transform(directions, self.rotation)
        if self.shape == "box":
            return _intersect_box(local_origin, local_dirs, self.size)
        if self.shape == "sphere":
            return _intersect_sphere(local_origin, local_dirs, self.size[0])
        return _intersect_cylinder(local_origin, local_dirs, self.size[0], self.size[1])

    def normals(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """World unit normals [N, 3] and object-local points [N, 3] at surface points [N, 3]."""
        local = _transform(points - self.center, self.rotation)
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
        return _transform(local_normals, self.rotation.T), local


def _safe_reciprocal(values: np.ndarray) -> np.ndarray:
    tiny = np.float32(1e-12)
    return 1.0 / np.where(np.abs(values) < tiny, np.where(values < 0, -tiny, tiny), values)


def _intersect_box(origin: np.ndarray, dirs: np.ndarray, half: np.ndarray) -> np.ndarray:
    # Slab test, one axis at a time (reductions over a length-3 axis are slow in numpy).
    t_enter, t_exit = None, None
    for axis in range(3):
        inverse = _safe_reciprocal(dirs[:, axis])
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
    b = _transform(dirs, origin)
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
        t_cap = (cap_y - oy) * _safe_reciprocal(dy)
        cap_x = ox + t_cap * dx
        cap_z = oz + t_cap * dz
        cap_hit = (t_cap > _NEAR) & (cap_x * cap_x + cap_z * cap_z <= radius * radius)
        t = np.where(cap_hit, np.minimum(t, t_cap), t)
    return t


@dataclasses.dataclass(frozen=True)
class Scene:
    """A room `[0, room_size]` (metres, y up) with objects and a point light.

    Room face f (surface id f in `cast`) is the wall at the low (f even) or high (f odd)
    end of axis f // 2; its inward normal is +/- that axis.
    """

    room_size: np.ndarray
    room_materials: tuple[Material, ...]
    objects: tuple[SceneObject, ...]
    light_position: np.ndarray
    ambient: float


@dataclasses.dataclass(frozen=True)
class Camera:
    """World-to-camera pose (`X_cam = rotation @ X_world + translation`) and intrinsics [4]."""

    rotation: np.ndarray
    translation: np.ndarray
    intrinsics: np.ndarray

    @property
    def center(self) -> np.ndarray:
        return -self.rotation.T @ self.translation


def example_rng(seed: int, split: str, index: int) -> np.random.Generator:
    """The generator of example `index` of `split`: independent of build order and workers."""
    split_code = zlib.crc32(split.encode())
    return np.random.default_rng(np.random.SeedSequence([int(seed), split_code, int(index)]))


def _random_color(rng: np.random.Generator) -> np.ndarray:
    return rng.uniform(0.08, 0.95, 3).astype(np.float32)


def _unit_vector(rng: np.random.Generator) -> np.ndarray:
    vector = rng.normal(size=3)
    return vector / np.linalg.norm(vector)


def random_material(rng: np.random.Generator, texture_probabilities: np.ndarray) -> Material:
    """A random solid texture; `texture_probabilities` [len(TEXTURES)] weights the kinds."""
    kind = TEXTURES[rng.choice(len(TEXTURES), p=texture_probabilities)]
    color_a = _random_color(rng)
    color_b = _random_color(rng)
    # Keep patterned surfaces contrasted enough to be visibly patterned.
    if np.abs(color_a - color_b).max() < 0.25:
        color_b = np.clip(1.0 - color_a, 0.05, 0.95).astype(np.float32)
    scale = float(rng.uniform(0.2, 0.8) if kind != "gradient" else rng.uniform(1.0, 4.0))
    lattice = (
        rng.uniform(0.0, 1.0, (_NOISE_LATTICE,) * 3).astype(np.float32) if kind == "noise" else None
    )
    return Material(
        kind=kind,
        color_a=color_a,
        color_b=color_b,
        scale=scale,
        direction=_unit_vector(rng).astype(np.float32),
        offset=rng.uniform(0.0, 10.0, 3).astype(np.float32),
        lattice=lattice,
    )


# Room surfaces: many plain (indoor scenes have large untextured areas); objects: patterned.
_ROOM_TEXTURES = np.array([0.45, 0.15, 0.1, 0.2, 0.1])
_FLOOR_TEXTURES = np.array([0.2, 0.35, 0.1, 0.1, 0.25])
_OBJECT_TEXTURES = np.array([0.2, 0.25, 0.2, 0.1, 0.25])


def look_at_rotation(forward: np.ndarray, roll: float) -> np.ndarray:
    """World-to-camera rotation [3, 3] of a camera looking along `forward` (world, y up).

    Camera axes: x right, y down, z forward; `roll` (radians) turns about z.
    """
    forward = forward / np.linalg.norm(forward)
    right = np.cross(forward, np.array([0.0, 1.0, 0.0]))
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    rotation = np.stack([right, down, forward])  # rows: camera axes in world coordinates
    roll_matrix = geometry.rotation_matrix(np.array([0.0, 0.0, roll]))
    return roll_matrix @ rotation


def _room_exit_distance(room_size: np.ndarray, origin: np.ndarray, direction: np.ndarray) -> float:
    bound = np.where(direction > 0, room_size, 0.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        distances = np.where(np.abs(direction) > 1e-9, (bound - origin) / direction, np.inf)
    return float(distances.min())


def sample_scene(
    rng: np.random.Generator, settings: SceneSettings
) -> tuple[Scene, np.ndarray, np.ndarray]:
    """A random room with objects in front of the first camera.

    Returns the scene and the first camera's world-to-camera rotation [3, 3] and
    centre [3] (world).
    """
    room_size = np.array(
        [rng.uniform(3.5, 8.0), rng.uniform(2.4, 3.5), rng.uniform(3.5, 8.0)], np.float64
    )
    margin = 0.6
    center = np.array(
        [
            rng.uniform(margin, room_size[0] - margin),
            rng.uniform(0.7, min(1.9, room_size[1] - margin)),
            rng.uniform(margin, room_size[2] - margin),
        ]
    )
    # Look into the room, not at a nearby wall.
    for _ in range(100):
        yaw = rng.uniform(-np.pi, np.pi)
        pitch = rng.uniform(-0.45, 0.3)
        forward = np.array(
            [np.cos(pitch) * np.sin(yaw), np.sin(pitch), np.cos(pitch) * np.cos(yaw)]
        )
        if _room_exit_distance(room_size, center, forward) > 2.5:
            break
    rotation = look_at_rotation(forward, rng.uniform(-0.15, 0.15))

    camera_matrix = geometry.intrinsics_matrix(
        np.asarray(settings.intrinsics, np.float64), settings.height, settings.width
    )
    inverse_k = np.linalg.inv(camera_matrix)
    objects = []
    num_objects = int(rng.integers(settings.min_objects, settings.max_objects + 1))
    for _ in range(num_objects):
        shape = SHAPES[rng.integers(len(SHAPES))]
        # Anchor on a ray through the central 80% of view 1 so the object is mostly in view.
        pixel = np.array(
            [
                rng.uniform(0.1, 0.9) * settings.width - 0.5,
                rng.uniform(0.1, 0.9) * settings.height - 0.5,
                1.0,
            ]
        )
        ray = rotation.T @ (inverse_k @ pixel)
        wall = _room_exit_distance(room_size, center, ray)
        depth = rng.uniform(1.0, max(1.1, min(0.85 * wall, 5.0)))
        extent = rng.uniform(0.08, 0.18) * depth + rng.uniform(0.0, 0.15)
        if shape == "box":
            size = extent * rng.uniform(0.4, 1.0, 3)
        elif shape == "sphere":
            size = np.array([extent * rng.uniform(0.5, 0.9)])
        else:
            size = extent * np.array([rng.uniform(0.3, 0.8), rng.uniform(0.5, 1.2)])
        upright = rng.uniform() < 0.5
        if upright:
            object_rotation = geometry.rotation_matrix(np.array([0.0, rng.uniform(0, np.pi), 0.0]))
        else:
            object_rotation = geometry.rotation_matrix(_unit_vector(rng) * rng.uniform(0, np.pi))
        obj = SceneObject(
            shape=shape,
            center=np.zeros(3),
            rotation=object_rotation.astype(np.float32),
            size=size.astype(np.float32),
            material=random_material(rng, _OBJECT_TEXTURES),
        )
        radius = obj.bounding_radius
        position = center + depth * ray
        if upright and rng.uniform() < 0.6:  # rests on the floor
            position[1] = radius if shape == "sphere" else float(size[1])
        # Inside the room, and far enough from the camera for any motion of view 2.
        position = np.clip(position, radius + 0.01, room_size - radius - 0.01)
        to_object = position - center
        distance = np.linalg.norm(to_object)
        min_distance = radius + settings.max_translation + 0.3
        if distance < min_distance:
            continue
        objects.append(dataclasses.replace(obj, center=position.astype(np.float32)))

    room_materials = tuple(
        random_material(rng, _FLOOR_TEXTURES if face == 2 else _ROOM_TEXTURES) for face in range(6)
    )
    light = np.array(
        [
            rng.uniform(0.2, 0.8) * room_size[0],
            room_size[1] - 0.1,
            rng.uniform(0.2, 0.8) * room_size[2],
        ],
        np.float32,
    )
    scene = Scene(
        room_size=room_size.astype(np.float32),
        room_materials=room_materials,
        objects=tuple(objects),
        light_position=light,
        ambient=float(rng.uniform(0.25, 0.45)),
    )
    return scene, rotation, center


def ray_directions(
    camera: Camera, height: int, width: int, pixels: np.ndarray | None = None
) -> np.ndarray:
    """World ray directions [H, W, 3] (camera-z component 1) through `pixels` [H, W, 2].

    `pixels` defaults to the pixel grid; a hit at distance s along a ray lies at
    camera-z depth s.
    """
    if pixels is None:
        pixels = geometry.pixel_grid(height, width)
    camera_matrix = geometry.intrinsics_matrix(
        np.asarray(camera.intrinsics, np.float64), height, width
    )
    inverse_k = np.linalg.inv(camera_matrix)
    world_from_pixel = (camera.rotation.T @ inverse_k).astype(np.float32)
    homogeneous = np.concatenate([pixels, np.ones_like(pixels[..., :1])], -1).astype(np.float32)
    directions = _transform(homogeneous.reshape(-1, 3), world_from_pixel.T)
    return directions.reshape(homogeneous.shape)


def _object_screen_box(
    obj: SceneObject, camera: Camera, height: int, width: int
) -> tuple[int, int, int, int]:
    """Pixel rows/cols [r0, r1) x [c0, c1) covering the object's bounding sphere."""
    radius = obj.bounding_radius
    corners = obj.center + radius * np.array(
        [[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], np.float64
    )
    in_camera = corners @ camera.rotation.T + camera.translation
    if np.any(in_camera[:, 2] <= 1e-3):
        return 0, height, 0, width
    camera_matrix = geometry.intrinsics_matrix(
        np.asarray(camera.intrinsics, np.float64), height, width
    )
    projected = in_camera @ camera_matrix.T
    pixels = projected[:, :2] / projected[:, 2:]
    c0, r0 = np.floor(pixels.min(0)).astype(int)
    c1, r1 = np.ceil(pixels.max(0)).astype(int) + 1
    return max(r0, 0), min(r1, height), max(c0, 0), min(c1, width)


def cast(
    scene: Scene,
    camera: Camera,
    height: int,
    width: int,
    pixels: np.ndarray | None = None,
    directions: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Camera-z depth and surface id of the first hit through each pixel.

    Args:
      scene, camera: what to render from where.
      height, width: image size (defines the pixel-index camera matrix).
      pixels: optional [H', W', 2] sub-pixel coordinates to cast through (for
        exact lookups); defaults to the pixel grid, which enables screen-space
        culling of the objects.
      directions: the precomputed `ray_directions` of `pixels`, if at hand.

    Returns:
      depth [H', W'] float32 metres (> 0 everywhere: the room is closed) and
      surface [H', W'] int32 (0..5 room faces, 6 + k object k).
    """
    origin = camera.center.astype(np.float32)
    if directions is None:
        directions = ray_directions(camera, height, width, pixels)
    # The room is a box seen from inside: the nearest exit over the three axes.
    room = scene.room_size
    depth, surface = None, None
    for axis in range(3):
        component = directions[..., axis]
        positive = component >= 0  # a zero component gets +inf distance, never -inf
        bound = np.where(positive, room[axis], np.float32(0.0))
        distance = (bound - origin[axis]) * _safe_reciprocal(component)
        face = (2 * axis + positive).astype(np.int32)
        if depth is None:
            depth, surface = distance, face
        else:
            closer = distance < depth
            depth = np.where(closer, distance, depth)
            surface = np.where(closer, face, surface)

    cull = pixels is None
    for index, obj in enumerate(scene.objects):
        if cull:
            r0, r1, c0, c1 = _object_screen_box(obj, camera, height, width)
            if r0 >= r1 or c0 >= c1:
                continue
        else:
            r0, r1, c0, c1 = 0, depth.shape[0], 0, depth.shape[1]
        block = directions[r0:r1, c0:c1]
        distance = obj.intersect(origin, block.reshape(-1, 3)).reshape(block.shape[:2])
        closer = distance < depth[r0:r1, c0:c1]
        depth[r0:r1, c0:c1][closer] = distance[closer]
        surface[r0:r1, c0:c1][closer] = ROOM_SURFACES + index
    return depth.astype(np.float32), surface


def shade(
    scene: Scene,
    camera: Camera,
    depth: np.ndarray,
    surface: np.ndarray,
    directions: np.ndarray,
) -> np.ndarray:
    """Lambertian + ambient colour [H, W, 3] float32 in [0, 1] of the hits from `cast`.

    Args:
      scene, camera: as given to `cast`.
      depth, surface: [H, W] outputs of `cast`.
      directions: [H, W, 3] the rays of `cast` (`ray_directions`).
    """
    height, width = depth.shape
    points = (camera.center.astype(np.float32) + depth[..., None] * directions).reshape(-1, 3)
    image = np.empty_like(points)
    # Group pixels by surface with one (radix) sort instead of a boolean mask per surface.
    flat_surface = surface.ravel().astype(np.uint8)
    order = np.argsort(flat_surface, kind="stable")
    counts = np.bincount(flat_surface, minlength=ROOM_SURFACES + len(scene.objects))
    ends = np.cumsum(counts)
    for surface_id in np.flatnonzero(counts):
        pixels = order[ends[surface_id] - counts[surface_id] : ends[surface_id]]
        surface_points = points[pixels]
        to_light = scene.light_position - surface_points
        light_distance = np.sqrt(np.einsum("nc,nc->n", to_light, to_light))
        if surface_id < ROOM_SURFACES:
            axis, sign = surface_id // 2, (1.0 if surface_id % 2 == 0 else -1.0)
            along_normal = sign * to_light[:, axis]  # the inward normal is an axis
            material = scene.room_materials[surface_id]
            texture_points = surface_points
        else:
            obj = scene.objects[surface_id - ROOM_SURFACES]
            normals, texture_points = obj.normals(surface_points)
            along_normal = np.einsum("nc,nc->n", normals, to_light)
            material = obj.material
        diffuse = np.maximum(along_normal / light_distance, 0.0)
        intensity = (scene.ambient + (1.0 - scene.ambient) * diffuse)[:, None]
        if material.kind == "plain":
            image[pixels] = material.color_a * intensity
        else:
            image[pixels] = material.albedo(texture_points) * intensity
    return image.reshape(height, width, 3)


def render_view(
    scene: Scene, camera: Camera, height: int, width: int
) -> tuple[np.ndarray, np.ndarray]:
    """RGB [H, W, 3] uint8 and camera-z depth [H, W] float32 of one view."""
    directions = ray_directions(camera, height, width)
    depth, surface = cast(scene, camera, height, width, directions=directions)
    image = shade(scene, camera, depth, surface, directions)
    return np.clip(image * 255.0 + 0.5, 0, 255).astype(np.uint8), depth


def sample_intrinsics(rng: np.random.Generator, settings: SceneSettings) -> np.ndarray:
    """Normalised intrinsics [4] of one view (jittered when `intrinsics_jitter` > 0)."""
    nominal = np.asarray(settings.intrinsics, np.float64)
    if settings.intrinsics_jitter == 0:
        return nominal
    jitter = settings.intrinsics_jitter
    return nominal * rng.uniform(1.0 - jitter, 1.0 + jitter, 4)


def _flow_percentile(depth1, camera_matrix1, camera_matrix2, rotation, translation) -> float:
    flow, z2 = geometry.depth_to_flow(depth1, camera_matrix1, camera_matrix2, rotation, translation)
    magnitude = np.linalg.norm(flow, axis=-1)[z2 > 0.05]
    return float(np.percentile(magnitude, 99)) if magnitude.size else 0.0


def sample_motion(
    rng: np.random.Generator,
    settings: SceneSettings,
    depth1: np.ndarray,
    intrinsics1: np.ndarray,
    intrinsics2: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """A hand-held-like relative motion (R [3, 3], t [3]; X2 = R X1 + t).

    Rotation about a uniform axis by up to `max_rotation_degrees`, translation in a
    uniform direction with norm in [min_translation, max_translation]; both are
    shrunk together until the 99th percentile of the true flow is below
    `max_flow_fraction * width` (translation never below `min_translation`).
    """
    height, width = settings.height, settings.width
    angle = np.radians(rng.uniform(0.0, settings.max_rotation_degrees))
    axis = _unit_vector(rng)
    direction = _unit_vector(rng)
    norm = rng.uniform(settings.min_translation, settings.max_translation)
    camera_matrix1 = geometry.intrinsics_matrix(intrinsics1, height, width)
    camera_matrix2 = geometry.intrinsics_matrix(intrinsics2, height, width)
    max_flow = settings.max_flow_fraction * width
    # Coarse depth is enough to bound the flow and keeps this cheap.
    stride = max(1, min(height, width) // 48)
    coarse_depth = depth1[::stride, ::stride].astype(np.float64)
    coarse_k1 = camera_matrix1.copy()
    coarse_k2 = camera_matrix2.copy()
    # Subsampling pixel-index coordinates: u_coarse = u / stride.
    scale = np.diag([1.0 / stride, 1.0 / stride, 1.0])
    coarse_k1, coarse_k2 = scale @ coarse_k1, scale @ coarse_k2
    for _ in range(6):
        rotation = geometry.rotation_matrix(axis * angle)
        translation = direction * norm
        # Flow in coarse pixels * stride = flow in full-resolution pixels.
        percentile = stride * _flow_percentile(
            coarse_depth, coarse_k1, coarse_k2, rotation, translation
        )
        if percentile <= max_flow:
            break
        shrink = 0.97 * max_flow / percentile
        angle *= shrink
        norm = max(norm * shrink, settings.min_translation)
    return rotation, translation


def sample_pair(
    rng: np.random.Generator, settings: SceneSettings
) -> tuple[Scene, Camera, Camera, np.ndarray, np.ndarray]:
    """The scene and both cameras of one example, with view 1 already rendered.

    View 1 is rendered here because the motion is bounded by its flow.

    Returns:
      scene, camera1, camera2, image1 [H, W, 3] uint8, depth1 [H, W] float32.
    """
    height, width = settings.height, settings.width
    scene, rotation1, center1 = sample_scene(rng, settings)
    intrinsics1 = sample_intrinsics(rng, settings)
    intrinsics2 = sample_intrinsics(rng, settings)
    camera1 = Camera(rotation1, -rotation1 @ center1, intrinsics1)
    image1, depth1 = render_view(scene, camera1, height, width)
    for _ in range(20):
        rotation, translation = sample_motion(rng, settings, depth1, intrinsics1, intrinsics2)
        camera2 = Camera(
            rotation @ rotation1, rotation @ camera1.translation + translation, intrinsics2
        )
        center2 = camera2.center
        # View 2 stays inside the room and outside every object.
        inside = np.all(center2 > 0.2) and np.all(center2 < scene.room_size - 0.2)
        clear = all(
            np.linalg.norm(center2 - obj.center) > obj.bounding_radius + 0.2
            for obj in scene.objects
        )
        if inside and clear:
            break
    return scene, camera1, camera2, image1, depth1


def render_pair(rng: np.random.Generator, settings: SceneSettings) -> dict[str, Any]:
    """One two-view example with exact geometry.

    Returns:
      A dict with image1, image2 [H, W, 3] uint8; depth1, depth2 [H, W] float32
      camera-z metres; intrinsics1, intrinsics2 [4] float32 normalised; rotation
      [3, 3], translation [3] float32 (X2 = R X1 + t, metres); gt_flow [H, W, 2]
      float32 pixels I1 -> I2 and gt_flow_valid [H, W] bool (lands inside view 2,
      in front of it and not occluded there).
    """
    scene, camera1, camera2, image1, depth1 = sample_pair(rng, settings)
    image2, depth2 = render_view(scene, camera2, settings.height, settings.width)
    rotation, translation = geometry.relative_pose(
        camera1.rotation, camera1.translation, camera2.rotation, camera2.translation
    )
    gt_flow, gt_flow_valid = geometry.ground_truth_flow(
        depth1, depth2, camera1.intrinsics, camera2.intrinsics, rotation, translation
    )
    return {
        "image1": image1,
        "image2": image2,
        "depth1": depth1,
        "depth2": depth2,
        "intrinsics1": np.asarray(camera1.intrinsics, np.float32),
        "intrinsics2": np.asarray(camera2.intrinsics, np.float32),
        "rotation": np.asarray(rotation, np.float32),
        "translation": np.asarray(translation, np.float32),
        "gt_flow": gt_flow,
        "gt_flow_valid": gt_flow_valid,
    }
