"""Ray casting of a closed, textured room: the scene, its camera, and one rendered view.

A vectorised numpy ray caster in the spirit of DeMoN's Scenes11: a closed room
(floor, four walls, ceiling) holding boxes, spheres and cylinders (`shapes`),
coloured by solid procedural textures with surface detail (`textures`) and lit by
ambient light plus one point light with Lambertian shading. Colour is a function of
the 3-D point only (no specular term), so a point looks the same from both views and
image 2 warped by the true flow reproduces image 1.

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

from . import shapes, textures
from .vector_math import safe_reciprocal, transform

# Room surfaces are ids 0..5 in the surface map; object k has id ROOM_SURFACES + k.
ROOM_SURFACES = 6
# Surfaces seen at a grazing angle stretch the footprint of a pixel (`textures`' detail
# fades with it); beyond this cosine between the ray and the normal the stretch is no
# longer followed (a floor far away keeps some detail rather than none).
_MIN_FOOTPRINT_COSINE = 0.25


@dataclasses.dataclass(frozen=True)
class Scene:
    """A room `[0, room_size]` (metres, y up) with objects and a point light.

    Room face f (surface id f in `cast`) is the wall at the low (f even) or high (f odd)
    end of axis f // 2; its inward normal is +/- that axis.
    """

    room_size: np.ndarray
    room_materials: tuple[textures.Material, ...]
    objects: tuple[shapes.SceneObject, ...]
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
    directions = transform(homogeneous.reshape(-1, 3), world_from_pixel.T)
    return directions.reshape(homogeneous.shape)


def _object_screen_box(
    obj: shapes.SceneObject, camera: Camera, height: int, width: int
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
        distance = (bound - origin[axis]) * safe_reciprocal(component)
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
        image[pixels] *= textures.detail_factors(
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
    """The texture kind [H, W] int8 (an index into `textures.TEXTURES`) of each pixel's
    surface, from a surface id map [H, W] (`cast`)."""
    materials = scene.room_materials + tuple(obj.material for obj in scene.objects)
    kinds = np.array([textures.TEXTURES.index(material.kind) for material in materials], np.int8)
    return kinds[surface]
