"""From two camera frames to metric depth: the runtime of a model exported by
`python -m experiments.export`.

    from gld.inference.runtime import DepthRuntime
    runtime = DepthRuntime.load("runs/robot/model.gldx")
    result = runtime.predict(frame1, frame2, intrinsics=(fx, fy, cx, cy), baseline=0.12)
    result["depth"]        # [H, W] metres at the frames' size
    result["points"]       # [H, W, 3] metres in camera 1's frame (with intrinsics)
    runtime(frame1, frame2, ranges=[(u, v, 1.73)])           # depth, scaled by a range reading
    runtime(frame1, frame2, rotation=R, translation=t)       # odometry: ||t|| is the baseline

Everything between the frames and the depth happens here, as `DepthPredictor` does it
with the training stack (the same `gld.inference.inputs` rules and the same numpy
resizing, `gld.inference.resampling`):
* frames: RGB (or greyscale, or RGBA) at any resolution, uint8 or float in [0, 1], one
  pair [H, W, C] or a batch [B, H, W, C]; any other dtype or range is refused;
* resized by area to the model's training resolution (aspect "resize" stretches a frame
  of another aspect ratio, with a warning; "crop" takes the centred crop and leaves NaN
  depth outside it);
* flow computed at that resolution as the model's training data computed it, recorded
  in the file's metadata ("flow"): OpenCV DIS with its preset (`gld.flow`), the flow
  network exported in the same file (JAX only), or the model's own flow network;
* the network (`gld.inference.deploy.DeployedModel`); a model trained given the pose
  takes the odometry (`rotation`, `translation`), one on its flow's essential matrix or
  reading a pose against the flow (refining it, derotating or triangulating the flow)
  takes the camera (`intrinsics`), and one given the odometry that reads it against the
  flow takes both;
* depth resized back to the frames' size, and scaled to metres by the baseline
  (`baseline=`, or ||translation|| of the odometry) or range readings (`ranges=`, (u, v,
  camera-z metres) in the frames' pixels; `gld.inference.metric_scale`). Without either
  it stays in baselines (`result["units"]`).

Requirements: jax, numpy and flatbuffers (`jax.export`'s deserialisation), plus
opencv-python-headless when the file's flow is OpenCV's or the model takes the pose of
its flow's essential matrix (`DepthRuntime.needs_opencv`). None of flax, optax, orbax,
TFDS or grain is imported; the README lists the exact set and a test runs this module
with nothing else importable.
"""

from __future__ import annotations

import importlib.util
from pathlib import Path
from typing import Any

import numpy as np

from gld import flow as flow_lib
from gld.inference import frame_pairs
from gld.inference.deploy import DeployedModel
from gld.inference.inputs import (
    ASPECT_MODES,
    PoseInputs,
    camera_matrix_from,
    resize_camera_matrix,
)


class DepthRuntime:
    """An exported model with everything from the frames to metric depth.

    Attributes:
      model: the exported network (`DeployedModel`).
      height, width: the resolution the network runs at (its training resolution).
      flow: how the flow is computed (the metadata's "flow": "estimator" is a
        `gld.flow` name, "flow_net" or "model").
      needs_opencv: whether a call needs OpenCV (classical flow or the essential matrix).
      needs_odometry: whether a call needs rotation= and translation= (a model trained
        given the relative pose).
      needs_camera: whether a call needs intrinsics= (a model on its flow's essential
        matrix, or reading a pose against the flow).
      reads: what the model needs besides the frames: "odometry" (rotation, translation),
        "camera" (intrinsics), "odometry and camera" (a model given the odometry that
        reads it against the flow) or None.
    """

    def __init__(self, model: DeployedModel, aspect: str = "resize"):
        if aspect not in ASPECT_MODES:
            raise ValueError(f"aspect must be one of {ASPECT_MODES}, got {aspect!r}")
        if model.flow is None:
            raise ValueError(
                f"the file has format version {model.metadata.get('format_version')}, which "
                "does not record how its flow is computed: export it again with this gld"
            )
        self.model, self.aspect = model, aspect
        self.height, self.width = model.height, model.width
        self.flow = model.flow
        estimator = self.flow.get("estimator")
        if estimator in flow_lib.RUNTIME_SETTINGS:
            expected = flow_lib.runtime_settings(estimator)
            if self.flow != expected:
                raise ValueError(
                    f"the file computes flow as {self.flow}, this gld's {estimator!r} as "
                    f"{expected}: use the gld the file was exported with, or export it again"
                )
        elif estimator == "flow_net" and model.flow_network is None:
            raise ValueError("the file records a flow network's flow but holds no network")
        elif estimator not in ("flow_net", "model"):
            raise ValueError(f"the file's flow estimator {estimator!r} is unknown to this gld")
        self._reads = PoseInputs.of(model.extra_inputs, "this runtime cannot give")
        self.needs_odometry = self._reads.odometry
        self.needs_camera = self._reads.needs_camera
        self.reads = {
            (False, False): None,
            (True, False): "odometry",
            (False, True): "camera",
            (True, True): "odometry and camera",
        }[self.needs_odometry, self.needs_camera]
        self.needs_opencv = estimator in flow_lib.RUNTIME_SETTINGS or self._reads.flow_pose
        if self.needs_opencv and importlib.util.find_spec("cv2") is None:
            raise ImportError(
                "this model's flow (or its essential-matrix pose) is computed with OpenCV: "
                "pip install opencv-python-headless"
            )

    @classmethod
    def load(cls, path: str | Path, aspect: str = "resize") -> DepthRuntime:
        """Reads a file of `experiments.export` (`DeployedModel.load`)."""
        return cls(DeployedModel.load(path), aspect)

    def model_flow(self, image1: np.ndarray, image2: np.ndarray) -> np.ndarray:
        """Flow [B, h, w, 2] (pixels, image1 -> image2) of frames already at the model's
        resolution, [B, h, w, 3] float32 in [0, 1], as the model's training data had it."""
        estimator = self.flow["estimator"]
        if estimator == "flow_net":
            return self.model.flow_network(image1, image2)
        if estimator == "model":  # only the shape is read
            return np.zeros((*image1.shape[:3], 2), np.float32)
        return np.stack(
            [flow_lib.estimate(a, b, estimator) for a, b in zip(image1, image2, strict=True)]
        )

    def predict(
        self,
        image1: Any,
        image2: Any,
        *,
        intrinsics: Any = None,
        baseline: Any = None,
        ranges: Any = None,
        rotation: Any = None,
        translation: Any = None,
    ) -> dict[str, Any]:
        """Depth of frame 1 from a pair of frames (or a batch of pairs).

        Args:
          image1, image2: [H, W, C] or [B, H, W, C] (C = 1, 3 or 4; or [H, W]), uint8 or
            float in [0, 1], any size, both alike.
          intrinsics: the frames' camera (fx, fy, cx, cy) in pixels ((0, 0) the centre of
            the top-left pixel) or a 3x3 K: gives "points", and is needed by models that
            take the motion from the flow's geometry (`needs_camera`).
          baseline: metres between the camera centres, one number or [B].
          ranges: range readings (u, v, camera-z metres) in the frames' pixels, [N, 3] for
            one pair, a sequence of B such arrays for a batch.
          rotation, translation: the odometry's relative pose ([3, 3], [3], or batched),
            X2 = R X1 + t, for a model trained given the pose (`needs_odometry`);
            without baseline= or ranges=, ||t|| in metres scales the depth.

        Returns:
          "depth" [H, W] at the frames' size (metres when scaled), "units" ("metres" or
          "baseline"), "scale" (metres per baseline), "scale_source" ("baseline",
          "ranges" or "none"), "flow" [h, w, 2] and "inv_depth" [h, w] at the model's
          resolution (in baselines), "global_params" where the model has them; with
          intrinsics, "points" [H, W, 3] in the depth's units. Batched inputs keep B.
        """
        frames = frame_pairs.model_frames(image1, image2, self.height, self.width, self.aspect)
        camera = None if intrinsics is None else camera_matrix_from(intrinsics)
        flow = self.model_flow(frames.image1, frames.image2)
        model_camera = None
        if camera is not None:
            model_camera = resize_camera_matrix(camera, frames.box, self.height, self.width)
        extra, norms = self._reads.keywords(
            flow, model_camera, rotation, translation, frames.single
        )
        if norms is not None and baseline is None and ranges is None:
            baseline = float(norms[0]) if frames.single else norms
        outputs = self.model.predict(frames.image1, frames.image2, flow, **extra)
        return frame_pairs.metric_outputs(
            {**outputs, "flow": flow},
            frames,
            baseline=baseline,
            ranges=ranges,
            camera_matrix=camera,
        )

    def __call__(self, image1: Any, image2: Any, **measurements: Any) -> np.ndarray:
        """Depth of frame 1 at the frames' size: `predict(...)["depth"]`."""
        return self.predict(image1, image2, **measurements)["depth"]
