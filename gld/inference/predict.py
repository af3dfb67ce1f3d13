"""Depth from two images with a trained model: one pair, a batch, or a whole recording.

    from gld.inference.predict import DepthPredictor
    predictor = DepthPredictor.from_workdir("runs/demo")
    depth = predictor(image1, image2)                     # [H, W], baseline units
    depth_m = predictor(image1, image2, baseline=0.12)    # metres, from odometry
    outputs = predictor.predict(image1, image2, ranges=[(320, 240, 1.7)],
                                intrinsics=(525.0, 525.0, 319.5, 239.5))
    outputs["depth"], outputs["units"], outputs["scale"], outputs["points"]

Scale. The model is trained with the pair's translation at ||t|| = 1, so it predicts
depth in units of the baseline. `baseline=` (metres between the two camera centres,
e.g. from odometry) or `ranges=` (readings (u, v, distance) of a range sensor in pixels
of the input image, camera-z metres) turn it into metres (`gld.inference.scale`); with neither
the depth stays in baseline units. `outputs["units"]` says which ("metres" or
"baseline"), `outputs["scale"]` the metres per unit (1 without a measurement) and
`outputs["scale_source"]` where it came from ("baseline", "ranges" or "none").

Inputs are checked and converted by rule (`gld.inference.inputs`: dtypes, channels,
sizes, aspect, flow, cameras).

`inv_depth`, `global_params` and the model's other outputs are at the model's
resolution, in baseline units.

A whole recording, frame by frame, is `gld.inference.recordings`'s.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import jax
import numpy as np

from gld import flow as flow_lib
from gld.inference import frame_pairs, resampling
from gld.inference.inputs import (
    ASPECT_MODES,
    PoseInputs,
    camera_matrix_from,
    resize_camera_matrix,
)
from gld.runs import trained_flow
from gld.runs import workdir as workdir_lib


class DepthPredictor:
    """A trained depth model with jit-compiled batched inference."""

    def __init__(
        self,
        model,
        variables,
        height: int,
        width: int,
        flow_method: str = flow_lib.DEFAULT_ESTIMATOR,
        aspect: str = "resize",
    ):
        if aspect not in ASPECT_MODES:
            raise ValueError(f"aspect must be one of {ASPECT_MODES}, got {aspect!r}")
        extra_inputs = tuple(getattr(model, "extra_inputs", ()))
        self._reads = PoseInputs.of(extra_inputs, "a predictor lacks")
        # "pose": the model was trained given the true relative pose (odometry here);
        # "flow_pose": the essential matrix's pose from its input flow; None: neither.
        self.given_pose = (
            "pose" if self._reads.odometry else "flow_pose" if self._reads.flow_pose else None
        )
        # Models that take the motion from the flow's geometry (the essential matrix's
        # pose, or reading a pose against the flow) need the camera.
        self.needs_camera = self._reads.needs_camera
        self.model, self.variables = model, variables
        self.height, self.width = height, width
        self.flow_method = flow_method
        self.aspect = aspect
        self._apply = jax.jit(
            lambda variables, image1, image2, flow, extra: model.apply(
                variables, image1, image2, flow, **extra
            )
        )

    @classmethod
    def from_workdir(
        cls, workdir: str | Path, step: int | None = None, **options: Any
    ) -> DepthPredictor:
        """Loads the latest (or given) checkpoint of a training workdir; `options` go to
        the constructor (flow_method, aspect)."""
        model, variables, config = workdir_lib.load_trained(workdir, step=step)
        return cls(model, variables, config.height, config.width, **options)

    def _given_pose(
        self,
        rotation: Any,
        translation: Any,
        model_flow: np.ndarray,
        camera_matrix: np.ndarray | None,
        box: tuple[int, int, int, int],
        single: bool,
        baseline: Any,
        ranges: Any,
    ) -> tuple[dict[str, np.ndarray], Any]:
        """The model's inputs besides the images and flow, by keyword (its given pose,
        the cameras, or both), and the baseline (||t|| of a given odometry when no other
        scale was given)."""
        camera = None
        if self.needs_camera and camera_matrix is not None:
            camera = resize_camera_matrix(camera_matrix, box, self.height, self.width)
        extra, norms = self._reads.keywords(model_flow, camera, rotation, translation, single)
        if norms is not None and baseline is None and ranges is None:
            baseline = norms if not single else float(norms[0])
        return extra, baseline

    def predict(
        self,
        image1: np.ndarray,
        image2: np.ndarray,
        flow: np.ndarray | None = None,
        *,
        baseline: float | Sequence[float] | np.ndarray | None = None,
        ranges: Any = None,
        intrinsics: Any = None,
        rotation: Any = None,
        translation: Any = None,
    ) -> dict[str, Any]:
        """Full model outputs at the model's resolution, plus depth at the input size.

        Args:
          image1, image2: [H, W, C] or [B, H, W, C] (C = 1, 3 or 4; or [H, W]), uint8 or
            float in [0, 1] (see the module docstring for the rules).
          flow: optional [H, W, 2] / [B, H, W, 2] flow I1 -> I2 in pixels of the input.
          baseline: metres between the camera centres: one number, or [B].
          ranges: range readings (u, v, distance in metres) in pixels of the input: an
            [N, 3] array for one pair, a sequence of B such arrays for a batch.
          intrinsics: the input camera's (fx, fy, cx, cy) in pixels or a 3x3 K. A model
            that takes the motion from its flow's geometry (`needs_camera`: trained on
            the pose from its flow, or reading a pose, its encoder's or a given one,
            against the flow: pose refinement, derotation, triangulation) needs them; a
            model given the odometry that reads it against the flow needs both.
          rotation, translation: the relative pose of the pair, [3, 3] and [3] (or [B, 3, 3]
            and [B, 3]), X2 = R X1 + t in the camera frame (x right, y down, z forward;
            `relative_pose` makes it from two camera-to-world poses): the odometry a
            model trained given the true pose (`given_pose == "pose"`) needs. Without
            `baseline=` or `ranges=`, ||t|| (metres) is the baseline.

        Returns:
          numpy arrays (batch axis dropped for a single pair): "depth" [H, W] at the input
          size, in metres when a scale was given; "depth_baseline_units" [H, W]; "scale"
          (metres per unit, 1 without a measurement); "units" ("metres" or "baseline");
          "scale_source" ("baseline", "ranges" or "none"); "inv_depth", "global_params"
          and the model's other outputs at the model's resolution; with intrinsics,
          "points" [H, W, 3] in the depth's units and "model_camera_matrix" [3, 3].

        Raises:
          ValueError: naming the argument that breaks the rules (shape, dtype, range,
            NaN, empty input, a bad reading or baseline).
        """
        frames = frame_pairs.model_frames(image1, image2, self.height, self.width, self.aspect)
        single, box = frames.single, frames.box
        batch_size, in_height, in_width = len(frames.image1), frames.in_height, frames.in_width
        resized1, resized2 = frames.image1, frames.image2
        camera_matrix = None if intrinsics is None else camera_matrix_from(intrinsics)
        if flow is not None:
            flow = np.asarray(flow, np.float32)
            if single:
                flow = flow[None]
            if flow.shape != (batch_size, in_height, in_width, 2):
                raise ValueError(
                    f"flow must be [{'' if single else 'B, '}H, W, 2] matching the images "
                    f"({in_height}x{in_width}), got shape {flow.shape[1 if single else 0 :]}"
                )
            non_finite = int(flow.size - np.count_nonzero(np.isfinite(flow)))
            if non_finite:
                raise ValueError(
                    f"flow contains {non_finite} NaN or inf value(s); fill or mask them "
                    f"before prediction (or omit flow= to estimate it)"
                )
        if flow is None:
            model_flow = np.stack(
                [
                    trained_flow.estimate_flow(a, b, self.flow_method)
                    for a, b in zip(resized1, resized2, strict=True)
                ]
            )
        else:
            flow_scale = np.array([self.width / box[3], self.height / box[2]], np.float32)
            model_flow = resampling.model_images(flow, box, self.height, self.width) * flow_scale
        extra, baseline = self._given_pose(
            rotation, translation, model_flow, camera_matrix, box, single, baseline, ranges
        )
        outputs = self._apply(self.variables, resized1 - 0.5, resized2 - 0.5, model_flow, extra)
        # Per-pair arrays only: filter banks and the pose g stands for are training aids.
        outputs = jax.device_get({k: v for k, v in outputs.items() if isinstance(v, jax.Array)})
        outputs = {k: np.asarray(v) for k, v in outputs.items()}
        return frame_pairs.metric_outputs(
            outputs, frames, baseline=baseline, ranges=ranges, camera_matrix=camera_matrix
        )

    def __call__(
        self,
        image1: np.ndarray,
        image2: np.ndarray,
        flow: np.ndarray | None = None,
        **options: Any,
    ) -> np.ndarray:
        """Depth of view 1 at the input size, [H, W] or [B, H, W]: metres with baseline=,
        ranges= or an odometry translation=, baseline units without. `options` are
        `predict`'s (baseline, ranges, intrinsics, rotation, translation)."""
        return self.predict(image1, image2, flow, **options)["depth"]


# ------------------------------------------------------- batch prediction over a recording
