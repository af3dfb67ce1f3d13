"""Random scenes and camera motion: what `renderer.render_pair` draws before it renders.

`SceneSettings` bounds the draw; `sample_scene` furnishes a random room (see
`raycast`) and places the first camera looking into it, `sample_motion` draws a
hand-held-like relative motion whose flow stays below a bound, and `sample_pair`
puts them together. Every random choice comes from the `numpy.random.Generator`
handed in, so a draw is a pure function of the generator's seed.
"""

from __future__ import annotations

import dataclasses
import zlib

import numpy as np

from gld import geometry

from . import raycast, shapes, textures

# DeMoN's nominal normalised intrinsics [fx/W, fy/H, cx/W, cy/H] (256x192 images).
NOMINAL_INTRINSICS = (0.89115971, 1.18821287, 0.5, 0.5)

SHAPES = ("box", "sphere", "cylinder")
_NOISE_LATTICE = 8  # periodic value-noise lattice size per axis
# The surface detail's largest relative change of the albedo (`textures.SurfaceDetail`).
DETAIL_CONTRAST = 1.0


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
      max_flow_fraction: the 99th percentile of the true flow magnitude with the
        nominal intrinsics is kept below this fraction of the image width (40 px at
        256x192) by shrinking the motion (varying intrinsics add their own flow).
      min_objects, max_objects: number of objects drawn (inclusive); an object that
        would come too close to the first camera is dropped.
      surface_detail: every surface carries band-limited detail that flow can track
        (`textures.SurfaceDetail`); False renders the surfaces' textures alone (large
        untextured areas). The detail draws nothing from the scene's generator, so
        geometry, poses, depth and true flow are the same either way.
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
    surface_detail: bool = True

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


def _random_color(rng: np.random.Generator) -> np.ndarray:
    return rng.uniform(0.08, 0.95, 3).astype(np.float32)


def _unit_vector(rng: np.random.Generator) -> np.ndarray:
    vector = rng.normal(size=3)
    return vector / np.linalg.norm(vector)


def surface_detail(color: np.ndarray, offset: np.ndarray) -> textures.SurfaceDetail:
    """The detail of a material, seeded by its drawn colour and offset (so that adding it
    draws nothing from the scene's generator and leaves the rest of the scene as it was)."""
    seed = zlib.crc32(np.asarray(color, np.float32).tobytes() + np.asarray(offset).tobytes())
    rng = np.random.default_rng(seed)
    octaves = len(textures.DETAIL_SPACINGS)
    return textures.SurfaceDetail(
        lattice=rng.uniform(0.0, 1.0, (textures.DETAIL_LATTICE,) * 3).astype(np.float32),
        octave_offsets=rng.uniform(0.0, textures.DETAIL_LATTICE, (octaves, 3)).astype(np.float32),
        contrast=DETAIL_CONTRAST,
    )


def random_material(
    rng: np.random.Generator, texture_probabilities: np.ndarray, detail: bool = True
) -> textures.Material:
    """A random solid texture; `texture_probabilities` [len(textures.TEXTURES)] weights the
    kinds; `detail` adds its surface detail (`surface_detail`)."""
    kind = textures.TEXTURES[rng.choice(len(textures.TEXTURES), p=texture_probabilities)]
    color_a = _random_color(rng)
    color_b = _random_color(rng)
    # Keep patterned surfaces contrasted enough to be visibly patterned.
    if np.abs(color_a - color_b).max() < 0.25:
        color_b = np.clip(1.0 - color_a, 0.05, 0.95).astype(np.float32)
    scale = float(rng.uniform(0.2, 0.8) if kind != "gradient" else rng.uniform(1.0, 4.0))
    lattice = (
        rng.uniform(0.0, 1.0, (_NOISE_LATTICE,) * 3).astype(np.float32) if kind == "noise" else None
    )
    direction = _unit_vector(rng).astype(np.float32)
    offset = rng.uniform(0.0, 10.0, 3).astype(np.float32)
    return textures.Material(
        kind=kind,
        color_a=color_a,
        color_b=color_b,
        scale=scale,
        direction=direction,
        offset=offset,
        lattice=lattice,
        detail=surface_detail(color_a, offset) if detail else None,
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
) -> tuple[raycast.Scene, np.ndarray, np.ndarray]:
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
        obj = shapes.SceneObject(
            shape=shape,
            center=np.zeros(3),
            rotation=object_rotation.astype(np.float32),
            size=size.astype(np.float32),
            material=random_material(rng, _OBJECT_TEXTURES, settings.surface_detail),
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
        random_material(
            rng, _FLOOR_TEXTURES if face == 2 else _ROOM_TEXTURES, settings.surface_detail
        )
        for face in range(6)
    )
    light = np.array(
        [
            rng.uniform(0.2, 0.8) * room_size[0],
            room_size[1] - 0.1,
            rng.uniform(0.2, 0.8) * room_size[2],
        ],
        np.float32,
    )
    scene = raycast.Scene(
        room_size=room_size.astype(np.float32),
        room_materials=room_materials,
        objects=tuple(objects),
        light_position=light,
        ambient=float(rng.uniform(0.25, 0.45)),
    )
    return scene, rotation, center


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
) -> tuple[raycast.Scene, raycast.Camera, raycast.Camera, np.ndarray, np.ndarray, np.ndarray]:
    """The scene and both cameras of one example, with view 1 already rendered.

    View 1 is rendered here because the motion is bounded by its flow.

    Returns:
      scene, camera1, camera2, image1 [H, W, 3] uint8, depth1 [H, W] float32, surface1
      [H, W] int32 (view 1's surface ids, `raycast.cast`).
    """
    height, width = settings.height, settings.width
    scene, rotation1, center1 = sample_scene(rng, settings)
    # The intrinsics have a stream of their own (spawning draws nothing from `rng`), so a
    # varying-intrinsics pair has the scene and the motion draws of the nominal pair of
    # the same generator: the varying split differs from the fixed one by its cameras.
    (intrinsics_rng,) = rng.spawn(1)
    intrinsics1 = sample_intrinsics(intrinsics_rng, settings)
    intrinsics2 = sample_intrinsics(intrinsics_rng, settings)
    camera1 = raycast.Camera(rotation1, -rotation1 @ center1, intrinsics1)
    image1, depth1, surface1 = raycast.render_view(scene, camera1, height, width)
    # The motion is the nominal pair's: drawn and bounded with the nominal intrinsics, so
    # the varying pair differs from it by its cameras alone (their change adds its own
    # flow on top of the bound).
    nominal = np.asarray(settings.intrinsics, np.float64)
    depth_nominal = depth1
    if settings.intrinsics_jitter:
        nominal_camera = raycast.Camera(rotation1, camera1.translation, nominal)
        _, depth_nominal, _ = raycast.render_view(scene, nominal_camera, height, width)
    for _ in range(20):
        rotation, translation = sample_motion(rng, settings, depth_nominal, nominal, nominal)
        camera2 = raycast.Camera(
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
    return scene, camera1, camera2, image1, depth1, surface1
