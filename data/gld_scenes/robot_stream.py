"""A simulated robot moving through one `gld_scenes` world: a `gld.online.stream.FrameStream`.

`SimulatedRobot(seed, settings)` draws one room (`scenes.sample_scene`), flies a small
robot through it at a fixed frame rate (smooth random speed and turns, steering clear
of the walls and the objects) and renders what its forward-looking camera sees. Each
frame carries the odometry pose (the true per-frame motion with gaussian noise,
integrated, so it drifts), one range reading at a fixed pixel (noisy, sometimes
dropped) and the simulation's truth (depth, true pose).

The world, the trajectory, the odometry noise and the range sensor each draw from a
generator of their own, spawned from the seed. Poses are cheap and images are not:
`frames(start)` integrates the motion from frame 0 without rendering up to `start`, so
frame i is the same whatever the start, and only the current frame is held in memory.
"""

from __future__ import annotations

import dataclasses
import itertools
from collections.abc import Iterator
from typing import Any

import numpy as np

from gld import geometry
from gld.online.stream import Frame

from . import raycast, scenes


@dataclasses.dataclass(frozen=True)
class World:
    """How a robot's world departs from `scenes.sample_scene`'s room.

    Attributes:
      intrinsics: the camera's normalised intrinsics (also used to place the objects).
      room_scale: the room's floor extents (x, z), the objects' and the light's x and z
        are multiplied by this; heights and object sizes are kept.
      pattern_scale: every material's pattern period (`textures.Material.scale`) is
        multiplied by this (> 1: coarser checkers, stripes, gradients and noise).
      tint: every material's colours are multiplied by this RGB factor.
      surface_detail: as `scenes.SceneSettings.surface_detail`.
    """

    intrinsics: tuple[float, float, float, float]
    room_scale: float
    pattern_scale: float
    tint: tuple[float, float, float]
    surface_detail: bool


WORLDS = {
    # The training worlds' room, camera and look.
    "training": World(scenes.NOMINAL_INTRINSICS, 1.0, 1.0, (1.0, 1.0, 1.0), True),
    # A wider view (80 x 64 degrees instead of 59 x 46), floors 1.6 times as long and wide
    # (5.6 to 12.8 m instead of 3.5 to 8 m), patterns twice as coarse, warm colours.
    "shifted": World((0.6, 0.8, 0.5, 0.5), 1.6, 2.0, (1.0, 0.8, 0.6), True),
}

# The rooms' lowest ceiling (`scenes.sample_scene`), metres.
_LOWEST_CEILING = 2.4
# Steering: the path ahead is probed at these distances (metres) in these directions
# (degrees from the heading, nearest first); a blocked heading turns the robot towards the
# nearest open direction at most at _MAX_TURN_RATE, reaching it in about _TURN_TIME
# seconds, at _AVOIDING_SPEED times its free speed.
_PROBE_DISTANCES = np.array([0.2, 0.5, 1.0])
_PROBE_ANGLES = np.radians([0.0] + [sign * a for a in range(15, 180, 15) for sign in (1, -1)])
_MAX_TURN_RATE = np.radians(60.0)
_TURN_TIME = 1.0
_AVOIDING_SPEED = 0.5
# Speed and turn rate follow their targets with this time constant (seconds): smooth.
_RESPONSE_TIME = 0.5
# Period (seconds) of the height and pitch oscillations.
_OSCILLATION_PERIOD = 4.0


@dataclasses.dataclass(frozen=True)
class RobotSettings:
    """Settings of a simulated robot's stream.

    Attributes:
      height, width: image size in pixels.
      length: number of frames; None for an endless stream.
      world: a key of `WORLDS`: "training" (the training worlds) or "shifted".
      frame_rate: frames per second.
      mean_speed: mean of the speed (m/s), a smooth random process clipped to
        [0.2, 2] times this.
      speed_deviation: the speed's standard deviation around its mean (m/s).
      turn_rate_deviation_degrees: the turn rate's (yaw rate's) standard deviation (deg/s).
      correlation_time: seconds over which the speed and the turn rate decorrelate.
      camera_height: the camera's mean height above the floor (metres).
      height_amplitude: the height's oscillation amplitude (metres).
      pitch_amplitude_degrees: the camera's pitch oscillation amplitude (degrees).
      camera_yaw_degrees: the camera's heading relative to the direction of travel
        (degrees, positive to the right): 0 looks ahead, where moving forward gives the
        flow of an expansion, and no flow at its centre whatever the depth; 90 looks
        sideways, where the flow is a translation's parallax.
      wall_margin: the camera stays at least this far (metres) from the walls.
      object_margin: the camera stays at least this far (metres) from every object's
        bounding sphere.
      odometry_translation_noise: standard deviation per axis of the odometry's
        per-frame translation error, as a fraction of the frame's step length.
      odometry_rotation_noise_degrees: standard deviation per axis (axis-angle, degrees)
        of the odometry's per-frame rotation error.
      range_noise: the range reading is the true depth times (1 + N(0, range_noise)).
      range_dropout: probability that a frame has no reading.
      max_range: beyond this true depth (metres) the sensor reads nothing.
      reading_pixel: (u, v) integer pixel of the range sensor; None is the centre pixel
        (width // 2, height // 2).
    """

    height: int = 96
    width: int = 128
    length: int | None = None
    world: str = "training"
    frame_rate: float = 10.0
    mean_speed: float = 0.3
    speed_deviation: float = 0.1
    turn_rate_deviation_degrees: float = 20.0
    correlation_time: float = 2.0
    camera_height: float = 1.0
    height_amplitude: float = 0.05
    pitch_amplitude_degrees: float = 3.0
    camera_yaw_degrees: float = 0.0
    wall_margin: float = 0.4
    object_margin: float = 0.3
    odometry_translation_noise: float = 0.02
    odometry_rotation_noise_degrees: float = 0.2
    range_noise: float = 0.01
    range_dropout: float = 0.1
    max_range: float = 10.0
    reading_pixel: tuple[int, int] | None = None

    def __post_init__(self):
        if self.height < 8 or self.width < 8:
            raise ValueError(
                f"height and width must be >= 8, got height={self.height}, width={self.width}"
            )
        if self.length is not None and self.length < 0:
            raise ValueError(f"length must be None or >= 0, got {self.length}")
        if self.world not in WORLDS:
            raise ValueError(f"world must be one of {sorted(WORLDS)}, got {self.world!r}")
        positive = ("frame_rate", "mean_speed", "correlation_time", "max_range")
        for name in positive:
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be > 0, got {getattr(self, name)}")
        non_negative = (
            "speed_deviation",
            "turn_rate_deviation_degrees",
            "height_amplitude",
            "object_margin",
            "odometry_translation_noise",
            "odometry_rotation_noise_degrees",
            "range_noise",
        )
        for name in non_negative:
            if not getattr(self, name) >= 0:
                raise ValueError(f"{name} must be >= 0, got {getattr(self, name)}")
        if not (
            0.1 <= self.camera_height - self.height_amplitude
            and self.camera_height + self.height_amplitude <= _LOWEST_CEILING - 0.1
        ):
            raise ValueError(
                f"camera_height +/- height_amplitude must stay in [0.1, "
                f"{_LOWEST_CEILING - 0.1}] m, got {self.camera_height} +/- "
                f"{self.height_amplitude}"
            )
        if not 0 <= self.pitch_amplitude_degrees <= 30:
            raise ValueError(
                f"pitch_amplitude_degrees must be in [0, 30], got {self.pitch_amplitude_degrees}"
            )
        if not -180 <= self.camera_yaw_degrees <= 180:
            raise ValueError(
                f"camera_yaw_degrees must be in [-180, 180], got {self.camera_yaw_degrees}"
            )
        if not 0 <= self.wall_margin <= 1.0:
            raise ValueError(f"wall_margin must be in [0, 1] m, got {self.wall_margin}")
        if not 0 <= self.range_dropout <= 1:
            raise ValueError(f"range_dropout must be in [0, 1], got {self.range_dropout}")
        if self.reading_pixel is not None:
            u, v = self.reading_pixel
            if not (0 <= u < self.width and 0 <= v < self.height):
                raise ValueError(
                    f"reading_pixel must lie in the {self.width}x{self.height} image, "
                    f"got {self.reading_pixel}"
                )


def build_world(
    rng: np.random.Generator, world: World, height: int, width: int
) -> tuple[raycast.Scene, np.ndarray, np.ndarray]:
    """The room of `world`: `scenes.sample_scene` at this size, changed as `world` says.

    Returns the scene and sample_scene's first camera rotation [3, 3] and centre [3]
    (world), the centre moved with the room.
    """
    settings = scenes.SceneSettings(
        height=height,
        width=width,
        intrinsics=world.intrinsics,
        surface_detail=world.surface_detail,
    )
    scene, rotation, center = scenes.sample_scene(rng, settings)
    stretch = np.array([world.room_scale, 1.0, world.room_scale], np.float32)
    tint = np.asarray(world.tint, np.float32)

    def restyle(material):
        return dataclasses.replace(
            material,
            color_a=material.color_a * tint,
            color_b=material.color_b * tint,
            scale=material.scale * world.pattern_scale,
        )

    objects = tuple(
        dataclasses.replace(obj, center=obj.center * stretch, material=restyle(obj.material))
        for obj in scene.objects
    )
    scene = raycast.Scene(
        room_size=scene.room_size * stretch,
        room_materials=tuple(restyle(material) for material in scene.room_materials),
        objects=objects,
        light_position=scene.light_position * stretch,
        ambient=scene.ambient,
    )
    return scene, rotation, center * stretch


@dataclasses.dataclass(frozen=True)
class _State:
    """What frame `index` has before rendering: poses and the range sensor's draws."""

    index: int
    true_rotation: np.ndarray
    true_translation: np.ndarray
    rotation: np.ndarray
    translation: np.ndarray
    range_noise: float
    range_dropout: float


class SimulatedRobot:
    """A robot flying through one `gld_scenes` room: a `FrameStream`.

    Attributes:
      height, width, length: as `settings` (the `FrameStream` attributes).
      seed, settings: what the stream was made from.
      world: `WORLDS[settings.world]`.
      scene: the room (`raycast.Scene`).
      intrinsics: [4] float32 normalised intrinsics of the camera.
      reading_pixel: (u, v) integer pixel of the range sensor.
    """

    def __init__(self, seed: int, settings: RobotSettings = RobotSettings()):
        self.seed = int(seed)
        self.settings = settings
        self.height, self.width, self.length = settings.height, settings.width, settings.length
        self.world = WORLDS[settings.world]
        world_seed, self._trajectory_seed, self._odometry_seed, self._range_seed = (
            np.random.SeedSequence(self.seed).spawn(4)
        )
        self.scene, start_rotation, self._start_center = build_world(
            np.random.default_rng(world_seed), self.world, self.height, self.width
        )
        forward = start_rotation[2]  # the camera's z axis in the world
        self._start_yaw = float(np.arctan2(forward[0], forward[2]))
        self.intrinsics = np.asarray(self.world.intrinsics, np.float32)
        self.reading_pixel = settings.reading_pixel
        if self.reading_pixel is None:
            self.reading_pixel = (self.width // 2, self.height // 2)
        self._object_centers = np.array([obj.center for obj in self.scene.objects]).reshape(-1, 3)
        self._object_radii = np.array([obj.bounding_radius for obj in self.scene.objects])

    def clearance(self, positions: np.ndarray) -> np.ndarray:
        """How far (metres) camera positions [N, 2] (x, z) are from breaking a margin.

        Negative where the camera, at any height of its oscillation, would come closer
        than `wall_margin` to a wall or `object_margin` to an object's bounding sphere.
        """
        settings = self.settings
        floor = self.scene.room_size[[0, 2]].astype(np.float64)
        walls = np.minimum(positions, floor - positions).min(-1) - settings.wall_margin
        # The nearest an object's centre comes to the band of camera heights.
        lowest = settings.camera_height - settings.height_amplitude
        highest = settings.camera_height + settings.height_amplitude
        centers = self._object_centers
        vertical = np.maximum(np.maximum(lowest - centers[:, 1], centers[:, 1] - highest), 0)
        horizontal = positions[:, None, :] - centers[None, :, [0, 2]]
        distance = np.sqrt(np.sum(horizontal**2, -1) + vertical**2)
        gaps = distance - self._object_radii - settings.object_margin
        return np.minimum(walls, gaps.min(-1, initial=np.inf))

    def _start(self, rng: np.random.Generator) -> np.ndarray:
        """The first position (x, z): sample_scene's camera, else the first clear draw."""
        position = self._start_center[[0, 2]].astype(np.float64)
        floor = self.scene.room_size[[0, 2]].astype(np.float64)
        for _ in range(1000):
            if self.clearance(position[None])[0] > 0:
                return position
            position = rng.uniform(0.0, floor)
        raise ValueError(f"no clear start position in the room of seed {self.seed}")

    def _steer(
        self, position: np.ndarray, yaw: float, turn_rate: float, blocked: bool
    ) -> float | None:
        """The turn rate (rad/s) that avoids what lies ahead; None when the way is open.

        Probes `_PROBE_DISTANCES` along each of `_PROBE_ANGLES` off the heading (the current
        turn's side first), turns towards the nearest open one, or the clearest if none
        is open. `blocked` (the last step was refused) counts the heading as closed.
        """
        angles = _PROBE_ANGLES * (1.0 if turn_rate >= 0 else -1.0)
        headings = yaw + angles
        offsets = np.stack([np.sin(headings), np.cos(headings)], -1)
        probes = position + _PROBE_DISTANCES[:, None, None] * offsets  # [D, A, 2]
        clearance = self.clearance(probes.reshape(-1, 2)).reshape(probes.shape[:2]).min(0)
        open_ = clearance > 0
        if blocked:
            open_[0] = False
        elif open_[0]:
            return None
        best = int(np.argmax(open_)) if open_.any() else int(np.argmax(clearance))
        return float(np.clip(angles[best] / _TURN_TIME, -_MAX_TURN_RATE, _MAX_TURN_RATE))

    def true_poses(self) -> Iterator[tuple[np.ndarray, np.ndarray]]:
        """The true world-to-camera poses (rotation [3, 3], translation [3]) of frames
        0, 1, ... (endless; cheap: nothing is rendered)."""
        settings = self.settings
        rng = np.random.default_rng(self._trajectory_seed)
        step_time = 1.0 / settings.frame_rate
        persistence = np.exp(-step_time / settings.correlation_time)
        innovation = np.sqrt(1.0 - persistence**2)
        response = 1.0 - np.exp(-step_time / _RESPONSE_TIME)
        turn_deviation = np.radians(settings.turn_rate_deviation_degrees)
        pitch_amplitude = np.radians(settings.pitch_amplitude_degrees)
        camera_yaw = np.radians(settings.camera_yaw_degrees)
        height_phase, pitch_phase = rng.uniform(0.0, 2 * np.pi, 2)
        position, yaw = self._start(rng), self._start_yaw
        speed = free_speed = settings.mean_speed
        turn_rate = free_turn_rate = 0.0
        blocked = False
        for index in itertools.count():
            phase = 2 * np.pi * index * step_time / _OSCILLATION_PERIOD
            height = settings.camera_height + settings.height_amplitude * np.sin(
                phase + height_phase
            )
            pitch = pitch_amplitude * np.sin(phase + pitch_phase)
            heading = yaw + camera_yaw
            forward = np.array(
                [np.cos(pitch) * np.sin(heading), np.sin(pitch), np.cos(pitch) * np.cos(heading)]
            )
            rotation = scenes.look_at_rotation(forward, 0.0)
            yield rotation, -rotation @ np.array([position[0], height, position[1]])

            # Speed and turn rate: mean-reverting random targets, overridden near obstacles.
            free_speed = (
                settings.mean_speed
                + persistence * (free_speed - settings.mean_speed)
                + innovation * settings.speed_deviation * rng.normal()
            )
            free_turn_rate = (
                persistence * free_turn_rate + innovation * turn_deviation * rng.normal()
            )
            target_speed = np.clip(free_speed, 0.2 * settings.mean_speed, 2 * settings.mean_speed)
            target_turn_rate = np.clip(free_turn_rate, -_MAX_TURN_RATE, _MAX_TURN_RATE)
            avoiding_turn_rate = self._steer(position, yaw, turn_rate, blocked)
            if avoiding_turn_rate is not None:
                target_speed, target_turn_rate = _AVOIDING_SPEED * target_speed, avoiding_turn_rate
            speed += response * (target_speed - speed)
            turn_rate += response * (target_turn_rate - turn_rate)
            yaw += turn_rate * step_time
            step = speed * step_time * np.array([np.sin(yaw), np.cos(yaw)])
            # The margins are never broken: a step that would break one is not taken.
            blocked = self.clearance((position + step)[None])[0] < 0
            if blocked:
                speed = 0.0
            else:
                position = position + step

    def _states(self) -> Iterator[_State]:
        """Frames 0, 1, ... before rendering: true and odometry poses, range draws."""
        settings = self.settings
        odometry_rng = np.random.default_rng(self._odometry_seed)
        range_rng = np.random.default_rng(self._range_seed)
        rotation_noise = np.radians(settings.odometry_rotation_noise_degrees)
        previous = None
        for index, (true_rotation, true_translation) in enumerate(self.true_poses()):
            if previous is None:
                rotation, translation = true_rotation, true_translation
            else:
                step_rotation, step_translation = geometry.relative_pose(
                    *previous, true_rotation, true_translation
                )
                step_length = np.linalg.norm(step_translation)  # = the centre's step
                step_rotation = (
                    geometry.rotation_matrix(rotation_noise * odometry_rng.normal(size=3))
                    @ step_rotation
                )
                step_translation = step_translation + (
                    settings.odometry_translation_noise * step_length * odometry_rng.normal(size=3)
                )
                rotation = step_rotation @ rotation
                translation = step_rotation @ translation + step_translation
            previous = true_rotation, true_translation
            yield _State(
                index,
                true_rotation,
                true_translation,
                rotation,
                translation,
                float(range_rng.normal()),
                float(range_rng.uniform()),
            )

    def _reading(self, depth: np.ndarray, state: _State) -> tuple[float, float, float] | None:
        """The range reading of a frame with true depth [H, W]; None when there is none."""
        settings = self.settings
        u, v = self.reading_pixel
        true_depth = float(depth[v, u])
        if (
            state.range_dropout < settings.range_dropout
            or not np.isfinite(true_depth)
            or true_depth > settings.max_range
        ):
            return None
        return float(u), float(v), true_depth * (1.0 + settings.range_noise * state.range_noise)

    def frames(self, start: int = 0) -> Iterator[Frame]:
        """The frames from position `start` on, in order; the same every call."""
        if start < 0:
            raise ValueError(f"start must be >= 0, got {start}")
        intrinsics = np.asarray(self.world.intrinsics, np.float64)
        for state in self._states():
            if self.length is not None and state.index >= self.length:
                return
            if state.index < start:
                continue
            camera = raycast.Camera(state.true_rotation, state.true_translation, intrinsics)
            image, depth, _ = raycast.render_view(self.scene, camera, self.height, self.width)
            yield Frame(
                index=state.index,
                time=state.index / self.settings.frame_rate,
                image=image,
                rotation=state.rotation,
                translation=state.translation,
                intrinsics=self.intrinsics.copy(),
                reading=self._reading(depth, state),
                depth=depth,
                true_rotation=state.true_rotation,
                true_translation=state.true_translation,
            )

    def describe(self) -> dict[str, Any]:
        """What the stream is (source, seed, world, rates, noise), JSON-ready."""
        return {
            "source": "gld_scenes robot",
            "seed": self.seed,
            **dataclasses.asdict(self.settings),
            "world_settings": dataclasses.asdict(self.world),
            "room_size": [float(x) for x in self.scene.room_size],
            "num_objects": len(self.scene.objects),
            "reading_pixel": list(self.reading_pixel),
        }
