"""Depth maps written to disk: 16-bit PNG in millimetres, .npy, colour previews, PLY.

* `write_depth_png`: single-channel 16-bit PNG, value = round(depth / 0.001), i.e.
  millimetres for metric depth; 0 means no prediction (not finite, not positive, or
  beyond 65.535 m). `gld.evaluation.stored_predictions.load_depth` reads it back (and `.npy`).
* `write_depth_npy`: float32 [H, W], NaN where there is no prediction.
* `write_preview`: image 1 beside its colourised inverse depth (magma, near = bright)
  and a colour bar giving the depth of its ticks in the depth's unit.
* `write_ply` / `read_ply`: binary little-endian point clouds (x, y, z float32 and
  optional red, green, blue uint8), from `point_cloud` (each pixel's 3-D point).
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from gld import geometry
from gld.evaluation import stored_predictions

PNG_DEPTH_SCALE = stored_predictions.DEFAULT_PNG_DEPTH_SCALE
_PNG_MAX = np.iinfo(np.uint16).max


def depth_to_png_values(depth: np.ndarray, depth_scale: float = PNG_DEPTH_SCALE) -> np.ndarray:
    """[H, W] depth -> [H, W] uint16 depth / depth_scale, 0 where there is no prediction
    (non-finite, <= 0, or too far for 16 bits)."""
    with np.errstate(invalid="ignore"):
        values = np.rint(np.asarray(depth, np.float64) / depth_scale)
        representable = np.isfinite(values) & (values > 0) & (values <= _PNG_MAX)
    return np.where(representable, values, 0).astype(np.uint16)


def _write_image(path: Path, image: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(str(path), image):
        raise OSError(f"cannot write {path}")


def write_depth_png(path: str | Path, depth: np.ndarray) -> int:
    """Writes metric depth as millimetres in a 16-bit PNG; returns how many pixels
    could not be stored (0 in the file)."""
    values = depth_to_png_values(depth)
    _write_image(Path(path), values)
    return int(np.count_nonzero(values == 0))


def write_depth_npy(path: str | Path, depth: np.ndarray) -> None:
    """Writes [H, W] float32 depth."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    np.save(path, np.asarray(depth, np.float32))


def inverse_depth_top(depth: np.ndarray) -> float:
    """The top of a preview's colour scale: the 99th percentile of the inverse depth of
    the pixels with a prediction (1.0 without any). Given several maps, their shared
    scale."""
    depth = np.asarray(depth, np.float64)
    valid = np.isfinite(depth) & (depth > 0)
    return float(np.percentile(1.0 / depth[valid], 99)) if np.any(valid) else 1.0


def colourise_inverse_depth(depth: np.ndarray, top: float | None = None) -> np.ndarray:
    """[H, W] depth -> [H, W, 3] uint8 RGB: inverse depth on the magma scale from 0 to
    `top` (default: the map's own, `inverse_depth_top`), black where there is no
    prediction."""
    depth = np.asarray(depth, np.float64)
    valid = np.isfinite(depth) & (depth > 0)
    inv_depth = np.zeros_like(depth)
    inv_depth[valid] = 1.0 / depth[valid]
    top = inverse_depth_top(depth) if top is None else top
    levels = np.clip(inv_depth / max(top, 1e-12) * 255.0, 0, 255).astype(np.uint8)
    colour = cv2.applyColorMap(levels, cv2.COLORMAP_MAGMA)
    colour[~valid] = 0
    return cv2.cvtColor(colour, cv2.COLOR_BGR2RGB)


# The colour bar's ticks, as fractions of the scale's top inverse depth (depth 1, 2 and
# 4 times the nearest depth shown at full brightness).
_BAR_TICKS = (1.0, 0.5, 0.25)


def colour_bar_ticks(top: float, unit: str) -> list[tuple[float, str]]:
    """The colour bar's ticks: (height fraction from the top, label), the label the depth
    at that level of inverse depth in `unit`."""
    return [
        (1.0 - fraction, f"{1.0 / (fraction * max(top, 1e-12)):.3g} {unit}")
        for fraction in _BAR_TICKS
    ]


def colour_bar(height: int, top: float, unit: str) -> np.ndarray:
    """[height, W, 3] uint8 RGB: the magma scale of `colourise_inverse_depth` (top:
    inverse depth `top`, bottom: 0, i.e. far), each tick labelled with its depth in
    `unit` ("m" for metric depth), on a white strip."""
    bar_width = 12
    scale = min(0.45, max(0.33, height / 400))
    ticks = colour_bar_ticks(top, unit)
    # Wide enough for the longest label ("58.5 x baseline" as much as "2.31 m").
    text_widths = [
        cv2.getTextSize(label, cv2.FONT_HERSHEY_SIMPLEX, scale, 1)[0][0] for _, label in ticks
    ]
    label_width = max(text_widths) + 10
    column = np.linspace(255, 0, height).astype(np.uint8)[:, None]
    bar = cv2.applyColorMap(np.repeat(column, bar_width, 1), cv2.COLORMAP_MAGMA)
    strip = np.full((height, bar_width + label_width, 3), 255, np.uint8)
    strip[:, :bar_width] = cv2.cvtColor(bar, cv2.COLOR_BGR2RGB)
    for position, label in ticks:
        row = int(round(position * (height - 1)))
        strip[row, bar_width : bar_width + 4] = 0
        baseline = min(max(row + 4, 10), height - 2)
        cv2.putText(
            strip, label, (bar_width + 6, baseline), cv2.FONT_HERSHEY_SIMPLEX, scale, (0, 0, 0)
        )
    return strip


def write_preview(
    path: str | Path,
    image: np.ndarray,
    depth: np.ndarray,
    *,
    top: float | None = None,
    unit: str = "m",
) -> None:
    """Writes image 1 ([H, W, 3] RGB uint8) beside its colourised inverse depth and the
    colour bar with the depth of each tick in `unit` ("m" for metric depth; the scale's
    top: `top`, default the map's own)."""
    top = inverse_depth_top(depth) if top is None else top
    colour = colourise_inverse_depth(depth, top)
    image = np.asarray(image, np.uint8)
    if image.shape[:2] != colour.shape[:2]:
        image = cv2.resize(image, colour.shape[1::-1], interpolation=cv2.INTER_AREA)
    panel = np.concatenate([image, colour, colour_bar(colour.shape[0], top, unit)], 1)
    _write_image(Path(path), cv2.cvtColor(panel, cv2.COLOR_RGB2BGR))


def point_cloud(
    depth: np.ndarray, camera_matrix: np.ndarray, image: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray | None]:
    """The 3-D points of the pixels with a prediction.

    Args:
      depth: [H, W] camera-z depth.
      camera_matrix: [3, 3] pixel-index K of the depth map's pixels.
      image: optional [H, W, 3] uint8 RGB, the points' colours.

    Returns:
      points [N, 3] float32 in the camera frame (x right, y down, z forward), one per
      pixel with finite, positive depth, in row-major order; colours [N, 3] uint8 or None.
    """
    depth = np.asarray(depth, np.float32)
    valid = np.isfinite(depth) & (depth > 0)
    points = geometry.backproject(np.where(valid, depth, 0.0), np.asarray(camera_matrix))
    colours = None if image is None else np.asarray(image, np.uint8)[valid]
    return points[valid].astype(np.float32), colours


def write_ply(path: str | Path, points: np.ndarray, colours: np.ndarray | None = None) -> None:
    """Writes points [N, 3] (and colours [N, 3] uint8) as a binary little-endian PLY."""
    points = np.asarray(points, np.float32).reshape(-1, 3)
    fields = [("x", "<f4"), ("y", "<f4"), ("z", "<f4")]
    if colours is not None:
        fields += [("red", "u1"), ("green", "u1"), ("blue", "u1")]
    vertices = np.empty(len(points), dtype=fields)
    vertices["x"], vertices["y"], vertices["z"] = points.T
    properties = ["property float x", "property float y", "property float z"]
    if colours is not None:
        colours = np.asarray(colours, np.uint8).reshape(-1, 3)
        vertices["red"], vertices["green"], vertices["blue"] = colours.T
        properties += ["property uchar red", "property uchar green", "property uchar blue"]
    header = "\n".join(
        ["ply", "format binary_little_endian 1.0", f"element vertex {len(points)}"]
        + properties
        + ["end_header"]
    )
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with path.open("wb") as stream:
        stream.write(header.encode("ascii") + b"\n")
        stream.write(vertices.tobytes())


_PLY_TYPES = {"float": "<f4", "float32": "<f4", "uchar": "u1", "uint8": "u1"}


def read_ply(path: str | Path) -> dict[str, np.ndarray]:
    """Reads a binary little-endian PLY of vertices as `write_ply` writes them.

    Returns:
      {"points": [N, 3] float32, "colours": [N, 3] uint8 (when present)}.
    """
    path = Path(path)
    content = path.read_bytes()
    end = content.find(b"end_header\n")
    if not content.startswith(b"ply\n") or end < 0:
        raise ValueError(f"{path}: not a PLY file")
    header = content[:end].decode("ascii").splitlines()
    if "format binary_little_endian 1.0" not in header:
        raise ValueError(f"{path}: only binary little-endian PLY is read")
    count, fields = 0, []
    for line in header:
        words = line.split()
        if words[:2] == ["element", "vertex"]:
            count = int(words[2])
        elif words[:1] == ["property"]:
            if words[1] not in _PLY_TYPES:
                raise ValueError(f"{path}: unsupported property {line!r}")
            fields.append((words[2], _PLY_TYPES[words[1]]))
    vertices = np.frombuffer(content, dtype=fields, count=count, offset=end + len("end_header\n"))
    result = {"points": np.stack([vertices[axis] for axis in "xyz"], -1).astype(np.float32)}
    if "red" in vertices.dtype.names:
        result["colours"] = np.stack([vertices[c] for c in ("red", "green", "blue")], -1)
    return result
