"""Solid procedural textures and surface detail: a surface's colour as a function of a 3-D point.

A `Material` colours a point (metres) by one of `TEXTURES`: plain, checkers, stripes,
gradients or value noise. Colour depends on the 3-D point only, so a point looks the
same from both views (`raycast` adds view-independent lighting).

A material may also carry surface detail (`SurfaceDetail`): multi-octave value noise
fixed to the surface that multiplies its albedo, so that every surface, plain ones
included, has something optical flow can track. One ray per pixel samples it with no
anti-aliasing, so each octave fades out as its lattice spacing shrinks from
`DETAIL_FADE_PIXELS[1]` to `DETAIL_FADE_PIXELS[0]` pixels on the surface: what stays is
resolved alike in both views (the fade depends on the view's distance and angle to the
surface, which two nearby views share nearly).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from .vector_math import transform

TEXTURES = ("plain", "checker", "stripes", "gradient", "noise")

# Surface detail: lattice spacings of its octaves (metres, halving from 0.4 m to 1.25 cm:
# 4 pixels at 1 m for 256x192 images), each octave's amplitude relative to the previous,
# and the fade of an octave between these two spacings in pixels on the surface.
DETAIL_SPACINGS = tuple(0.4 / 2**octave for octave in range(6))
DETAIL_PERSISTENCE = 0.65
DETAIL_FADE_PIXELS = (2.0, 4.0)
DETAIL_LATTICE = 16  # periodic lattice size per axis (a power of two)


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
            weight = 0.5 + 0.5 * np.sin(2.0 * np.pi * transform(coords, self.direction))
        elif self.kind == "gradient":
            weight = np.clip(transform(coords, self.direction), 0.0, 1.0)
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
