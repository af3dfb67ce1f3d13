"""What both predictors do around their network: frames in, metric depth out.

`DepthPredictor` (the live model) and `DepthRuntime` (an exported file) take the same
frames by the same rules and return the same outputs; only the flow and the network
between these two steps differ.

    frames = model_frames(image1, image2, height, width, aspect)   # checked, resized
    ...the flow and the network at the model's resolution...
    outputs = metric_outputs(network_outputs, frames, baseline=..., ranges=..., camera_matrix=K)

numpy and `gld.geometry` only (the runtime runs where the training stack is absent).
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

from gld import geometry
from gld.inference import metric_scale, resampling
from gld.inference.inputs import _as_rgb_float, crop_box, resize_camera_matrix, warn_if_stretched


@dataclasses.dataclass(frozen=True)
class ModelFrames:
    """A pair (or batch of pairs) of frames at the model's resolution.

    Attributes:
      image1, image2: [B, h, w, 3] float32 in [0, 1], resized by area.
      box: (top, left, height, width) of the input that was resized (`inputs.crop_box`).
      in_height, in_width: the input's size.
      single: whether one pair was given (outputs drop the batch axis).
    """

    image1: np.ndarray
    image2: np.ndarray
    box: tuple[int, int, int, int]
    in_height: int
    in_width: int
    single: bool


def model_frames(
    image1: Any, image2: Any, height: int, width: int, aspect: str, stacklevel: int = 3
) -> ModelFrames:
    """Both frames by `gld.inference.inputs`' rules, checked alike, cropped by `aspect`
    and resized to height x width (a stretch warns, `stacklevel` above the caller)."""
    first, single, channels1 = _as_rgb_float(image1, "image1")
    second, single2, channels2 = _as_rgb_float(image2, "image2")
    if first.shape != second.shape or single != single2:
        raise ValueError(
            f"image1 and image2 must have the same shape, got {np.shape(image1)} and "
            f"{np.shape(image2)}"
        )
    if channels1 != channels2:
        raise ValueError(
            f"image1 has {channels1} channel(s) and image2 {channels2}: give both images "
            "of a pair in the same format"
        )
    _, in_height, in_width, _ = first.shape
    box = crop_box(in_height, in_width, height, width, aspect)
    warn_if_stretched(box, height, width, aspect, stacklevel=stacklevel + 1)
    return ModelFrames(
        resampling.model_frames(first, box, height, width),
        resampling.model_frames(second, box, height, width),
        box,
        in_height,
        in_width,
        single,
    )


def metric_outputs(
    outputs: dict[str, np.ndarray],
    frames: ModelFrames,
    *,
    baseline: Any,
    ranges: Any,
    camera_matrix: np.ndarray | None,
) -> dict[str, Any]:
    """The network's batched outputs (with "inv_depth" [B, h, w]) and, at the input's
    size: "depth" (metres when scaled), "depth_baseline_units", "scale" (metres per
    baseline), "units", "scale_source"; with a camera, "points" [H, W, 3] and the
    camera the model saw, "model_camera_matrix". Without the batch axis for one pair."""
    depth = resampling.depth_at_input(
        outputs["inv_depth"], frames.box, frames.in_height, frames.in_width
    )
    scales, source = metric_scale.pair_scales(depth, baseline, ranges, frames.single)
    outputs = {
        **outputs,
        "depth_baseline_units": depth,
        "depth": depth * scales[:, None, None],
        "scale": scales,
    }
    if camera_matrix is not None:
        points = geometry.backproject(outputs["depth"], camera_matrix)
        outputs["points"] = points.astype(np.float32)
    if frames.single:
        outputs = {key: value[0] for key, value in outputs.items()}
    outputs["units"] = "baseline" if source == "none" else "metres"
    outputs["scale_source"] = source
    if camera_matrix is not None:
        height, width = frames.image1.shape[1:3]
        outputs["model_camera_matrix"] = resize_camera_matrix(
            camera_matrix, frames.box, height, width
        )
    return outputs
