"""Ray casting of a closed, textured room: the scene, its surfaces, and one rendered view.

A vectorised numpy ray caster in the spirit of DeMoN's Scenes11: a closed room
(floor, four walls, ceiling) holding boxes, spheres and cylinders (`SceneObject`),
coloured by solid procedural textures (`Material`: plain, checkers, stripes,
gradients, value noise) and lit by ambient light plus one point light with
Lambertian shading. Colour is a function of the 3-D point only (no specular term),
so a point looks the same from both views and image 2 warped by the true flow
reproduces image 1.

A material may also carry surface detail (`SurfaceDetail`): multi-octave value noise
fixed to the surface that multiplies its albedo, so that every surface, plain ones
included, has something optical flow can track. One ray per pixel samples it with no
anti-aliasing, so each octave fades out as its lattice spacing shrinks from
`DETAIL_FADE_PIXELS[1]` to `DETAIL_FADE_PIXELS[0]` pixels on the surface: what stays is
resolved alike in both views (the fade depends on the view's distance and angle to the
surface, which two nearby views share nearly).

Geometry follows `gld.geometry`: pixel (0, 0) is the centre of the top-left
pixel, intrinsics are normalised `[fx/W, fy/H, cx/W, cy/H]`, cameras are
world-to-camera `X_cam = R X_world + t`. The world has y pointing up, the floor at
y = 0. Rays are cast along `R^T K^-1 [u, v, 1]`, whose camera-z component is 1, so
the hit distance along a ray *is* camera-z depth.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from gld import geometry

TEXTURES = ("plain", "checker", "stripes", "gradient", "noise")
# Room surfaces are ids 0..5 in the surface map; object k has id ROOM_SURFACES + k.
ROOM_SURFACES = 6
_NEAR = 1e-3  # metres; ignores self-hits of a ray leaving a surface

# Surface detail: lattice spacings of its octaves (metres, halving from 0.4 m to 1.25 cm:
# 4 pixels at 1 m for 256x192 images), each octave's amplitude relative to the previous,
# and the fade of an octave between these two spacings in pixels on the surface.
DETAIL_SPACINGS = tuple(0.4 / 2**octave for octave in range(6))
DETAIL_PERSISTENCE = 0.65
DETAIL_FADE_PIXELS = (2.0, 4.0)
DETAIL_LATTICE = 16  # periodic lattice size per axis (a power of two)
# Surfaces seen at a grazing angle stretch the footprint of a pixel; beyond this cosine
# between the ray and the normal the stretch is no longer followed (a floor far away
# keeps some detail rather than none).
_MIN_FOOTPRINT_COSINE = 0.25


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
    detail: SurfaceDetail | None = None

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


@dataclasses.dataclass(frozen=True)
class SurfaceDetail:
    """Band-limited multi-octave value noise that multiplies a material's albedo.

    `lattice` [DETAIL_LATTICE] * 3 holds the noise samples, `octave_offsets`
    [len(DETAIL_SPACINGS), 3] shift each octave (lattice units) so the octaves do not
    share lattice points, and `contrast` is the largest relative change of the albedo
    (the albedo is scaled by 1 + contrast * d, d in [-1, 1]).
    """

    lattice: np.ndarray
    octave_offsets: np.ndarray
    contrast: float

    def factor(self, points: np.ndarray, footprint: np.ndarray) -> np.ndarray:
        """The albedo's multiplier [N] at surface points [N, 3] (metres, in the frame the
        detail is fixed to) whose pixels cover `footprint` [N] metres of the surface."""
        return detail_factors((self,), np.zeros(len(points), np.int64), points, footprint)


def detail_factors(
    details: tuple[SurfaceDetail, ...],
    which: np.ndarray,
    points: np.ndarray,
    footprint: np.ndarray,
) -> np.ndarray:
    """`SurfaceDetail.factor` of many surfaces at once: point n has detail `which[n]`.

    Args:
      details: the surfaces' details.
      which: [N] int, an index into `details` per point.
      points: [N, 3] metres, each in the frame its detail is fixed to.
      footprint: [N] metres of the surface one pixel covers at the point.

    Returns:
      [N] float32 multipliers of the albedo, 1 + contrast * d with d in [-1, 1].
    """
    lattices = np.stack([detail.lattice for detail in details])
    octave_offsets = np.stack([detail.octave_offsets for detail in details])
    contrast = np.array([detail.contrast for detail in details], np.float32)[which]
    total = np.zeros(len(points), np.float32)
    weight_sum = 0.0
    low, high = DETAIL_FADE_PIXELS
    for octave, spacing in enumerate(DETAIL_SPACINGS):
        amplitude = DETAIL_PERSISTENCE**octave
        weight_sum += amplitude
        fade = np.clip((spacing / footprint - low) / (high - low), 0.0, 1.0)
        visible = np.flatnonzero(fade > 0)
        if not visible.size:
            continue
        fade = fade[visible]
        fade = fade * fade * (3.0 - 2.0 * fade)
        layers = which[visible]
        coords = points[visible] / np.float32(spacing) + octave_offsets[layers, octave]
        noise = _value_noise(lattices, coords, layers)
        total[visible] += (amplitude * fade * (2.0 * noise - 1.0)).astype(np.float32)
    return 1.0 + contrast * total / np.float32(weight_sum)


def _value_noise(
    lattice: np.ndarray, coords: np.ndarray, layers: np.ndarray | None = None
) -> np.ndarray:
    """Smooth periodic value noise in [0, 1] at coords [N, 3] (lattice units).

    `lattice` is [L, L, L], or [S, L, L, L] with `layers` [N] choosing each point's."""
    size = lattice.shape[-1]  # a power of two, so `& (size - 1)` wraps indices
    values = lattice.ravel()
    base = np.floor(coords)
    frac = coords - base
    frac = frac * frac * (3.0 - 2.0 * frac)  # smoothstep: continuous derivative
    low = base.astype(np.int64) & (size - 1)
    high = (low + 1) & (size - 1)
    x0, x1 = low[:, 0] * size * size, high[:, 0] * size * size
    if layers is not None:
        x0 = x0 + layers * size**3
        x1 = x1 + layers * size**3
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
    flat_directions = directions.reshape(-1, 3)
    flat_depth = depth.ravel()
    image = np.empty_like(points)
    # A pixel's width on a surface facing the camera at camera-z depth d is d / focal.
    focal_pixels = np.float32(np.sqrt(camera.intrinsics[0] * width * camera.intrinsics[1] * height))
    # Group pixels by surface with one (radix) sort instead of a boolean mask per surface.
    flat_surface = surface.ravel().astype(np.uint8)
    order = np.argsort(flat_surface, kind="stable")
    counts = np.bincount(flat_surface, minlength=ROOM_SURFACES + len(scene.objects))
    ends = np.cumsum(counts)
    # The surface detail of every pixel is computed at once, after the loop.
    detailed_pixels, detailed_points, footprints, detail_index, details = [], [], [], [], []
    for surface_id in np.flatnonzero(counts):
        pixels = order[ends[surface_id] - counts[surface_id] : ends[surface_id]]
        surface_points = points[pixels]
        to_light = scene.light_position - surface_points
        light_distance = np.sqrt(np.einsum("nc,nc->n", to_light, to_light))
        rays = flat_directions[pixels]
        if surface_id < ROOM_SURFACES:
            axis, sign = surface_id // 2, (1.0 if surface_id % 2 == 0 else -1.0)
            along_normal = sign * to_light[:, axis]  # the inward normal is an axis
            material = scene.room_materials[surface_id]
            texture_points = surface_points
            ray_along_normal = np.abs(rays[:, axis])
        else:
            obj = scene.objects[surface_id - ROOM_SURFACES]
            normals, texture_points = obj.normals(surface_points)
            along_normal = np.einsum("nc,nc->n", normals, to_light)
            material = obj.material
            ray_along_normal = np.abs(np.einsum("nc,nc->n", normals, rays))
        diffuse = np.maximum(along_normal / light_distance, 0.0)
        intensity = (scene.ambient + (1.0 - scene.ambient) * diffuse)[:, None]
        if material.kind == "plain":
            image[pixels] = material.color_a * intensity
        else:
            image[pixels] = material.albedo(texture_points) * intensity
        if material.detail is not None:
            cosine = ray_along_normal / np.sqrt(np.einsum("nc,nc->n", rays, rays))
            footprints.append(
                flat_depth[pixels] / (focal_pixels * np.maximum(cosine, _MIN_FOOTPRINT_COSINE))
            )
            detailed_pixels.append(pixels)
            detailed_points.append(texture_points)
            detail_index.append(np.full(len(pixels), len(details)))
            details.append(material.detail)
    if details:
        pixels = np.concatenate(detailed_pixels)
        image[pixels] *= detail_factors(
            tuple(details),
            np.concatenate(detail_index),
            np.concatenate(detailed_points),
            np.concatenate(footprints),
        )[:, None]
    return image.reshape(height, width, 3)


def render_view(
    scene: Scene, camera: Camera, height: int, width: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """RGB [H, W, 3] uint8, camera-z depth [H, W] float32 and surface id [H, W] int32
    (as `cast`) of one view."""
    directions = ray_directions(camera, height, width)
    depth, surface = cast(scene, camera, height, width, directions=directions)
    image = shade(scene, camera, depth, surface, directions)
    return np.clip(image * 255.0 + 0.5, 0, 255).astype(np.uint8), depth, surface


def texture_kinds(scene: Scene, surface: np.ndarray) -> np.ndarray:
    """The texture kind [H, W] int8 (an index into `TEXTURES`) of each pixel's surface, from
    a surface id map [H, W] (`cast`)."""
    materials = scene.room_materials + tuple(obj.material for obj in scene.objects)
    kinds = np.array([TEXTURES.index(material.kind) for material in materials], np.int8)
    return kinds[surface]
