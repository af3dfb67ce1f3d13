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

Inputs, by rule:
* RGB images [H, W, C] (one pair) or [B, H, W, C] (a batch), any size, uint8 (0..255)
  or float in [0, 1]. Greyscale ([H, W], [H, W, 1], [B, H, W, 1]) is converted by
  replicating the channel (the model was trained on colour: expect worse depth);
  RGBA is converted by dropping alpha. Both images of a pair must have the same size
  and channels. Other dtypes (uint16, int, bool) are refused: their range is
  ambiguous, so scale them to uint8 or [0, 1] yourself. Empty images and empty
  batches are refused.
* Size: images are resized (OpenCV area) to the resolution the model was trained at,
  flow is computed there (OpenCV DIS) unless given, and depth is resized back to the
  input size. An input of another aspect ratio is, with `aspect="resize"` (default),
  stretched to the training size, which distorts the geometry the model sees (a
  `UserWarning` says by how much); with `aspect="crop"`, the centred crop of the
  training aspect ratio is used, and depth outside it is NaN.
* `flow=`: [H, W, 2] flow I1 -> I2 in pixels of the input; NaN or inf is refused.
* `intrinsics=`: fx, fy, cx, cy in pixels of the input image ((0, 0) the centre of the
  top-left pixel, as OpenCV) or a 3x3 K. With them, `outputs["points"]` holds each
  pixel's 3-D point in the camera frame (in the depth's units) and
  `outputs["model_camera_matrix"]` the camera the model saw after crop and resize.

`inv_depth`, `global_params` and the model's other outputs are at the model's
resolution, in baseline units.

A whole recording (`python -m experiments.predict`):

    frames = ImageFolderFrames(image_paths)          # or VideoFrames("rec.mp4")
    pairs = frame_pairs(len(frames), frame_gap=1)    # or read_pairs_file(path, frames.names)
    ranges = read_range_readings("range.csv", frames.names, frames.read(0).shape[:2])
    plan = plan_recording(pairs, ranges=ranges)      # or positions=camera centres [F, 3]
    predict_recording(predictor, frames, plan, "out", depth_format="png", previews=True)

Frames are read when a batch needs them and kept only while later pairs may use them
(a bounded cache), so a long recording never sits in memory. A pair (i, j) predicts
frame i's depth; its scale comes from frame i's range readings or from the distance
between the two frames' camera positions. Pairs without a measurement (no reading on
frame i; a baseline not above `min_baseline`) are skipped and counted; with neither
source, depth stays in baseline units. The output folder holds:

    depth/<frame1>__<frame2>.png   16-bit millimetres (metric depth only), or .npy float32
    preview/<frame1>__<frame2>.png image 1 beside its colourised inverse depth
    ply/<frame1>__<frame2>.ply     binary PLY point cloud in the depth's units
    pairs.csv                      one row per written pair: frames, scale, source, units
    summary.json                   counts, units, skipped pairs by reason, settings
"""

from __future__ import annotations

import collections
import csv
import dataclasses
import json
import warnings
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import cv2
import jax
import numpy as np

from gld import flow as flow_lib
from gld import flow_pose, geometry
from gld.flow_pose import FLOW_POSE_KEYS
from gld.inference import depth_io
from gld.inference import scale as scale_lib
from gld.models.global_local import CAMERA_INPUTS, GIVEN_POSE_INPUTS
from gld.runs import trained_flow
from gld.runs import workdir as workdir_lib

ASPECT_MODES = ("resize", "crop")
# Aspect ratios closer than this are the same shape at another resolution.
_ASPECT_TOLERANCE = 0.01
_CHANNELS = (1, 3, 4)


def _as_rgb_float(image: Any, name: str) -> tuple[np.ndarray, bool, int]:
    """An image or batch by the module's rules -> ([B, H, W, 3] float32 in [0, 1],
    whether it was a single image, its number of channels)."""
    image = np.asarray(image)
    if image.ndim == 2:
        image, single = image[None, ..., None], True
    elif image.ndim == 3:
        if image.shape[-1] not in _CHANNELS:
            raise ValueError(
                f"{name} must be [H, W], [H, W, C] or [B, H, W, C] with C in {_CHANNELS} "
                f"(a batch of greyscale images needs its channel axis: [B, H, W, 1]), got "
                f"shape {image.shape}"
            )
        image, single = image[None], True
    elif image.ndim == 4:
        if image.shape[-1] not in _CHANNELS:
            raise ValueError(
                f"{name} must be [B, H, W, C] with C in {_CHANNELS}, got shape {image.shape}"
            )
        single = False
    else:
        raise ValueError(
            f"{name} must be [H, W], [H, W, C] or [B, H, W, C], got shape {image.shape}"
        )
    batch_size, height, width, channels = image.shape
    if batch_size == 0:
        raise ValueError(f"{name} is an empty batch (shape {image.shape})")
    if height == 0 or width == 0:
        raise ValueError(f"{name} is empty: {height}x{width} pixels (shape {image.shape})")
    if image.dtype == np.uint8:
        image = image.astype(np.float32) / 255.0
    elif np.issubdtype(image.dtype, np.floating):
        if not np.all(np.isfinite(image)):
            raise ValueError(f"{name} contains NaN or inf")
        if image.min() < 0.0 or image.max() > 1.0:
            raise ValueError(
                f"float {name} must lie in [0, 1], got [{image.min():.3g}, {image.max():.3g}]"
            )
        image = image.astype(np.float32)
    else:
        raise ValueError(
            f"{name} has dtype {image.dtype}; images must be uint8 (0..255) or float in "
            f"[0, 1] (scale 16-bit or integer images yourself, e.g. image / 65535.0)"
        )
    if channels == 1:
        image = np.repeat(image, 3, axis=-1)
    elif channels == 4:
        image = image[..., :3]
    return image, single, channels


def check_image(image: Any, name: str) -> None:
    """Raises ValueError, naming `name`, when an image breaks the module's input rules."""
    _as_rgb_float(image, name)


def camera_matrix_from(intrinsics: Any) -> np.ndarray:
    """fx, fy, cx, cy (pixels) or a 3x3 K -> [3, 3] float64 K, checked."""
    values = np.asarray(intrinsics, np.float64)
    if values.shape == (4,):
        fx, fy, cx, cy = values
    elif values.shape == (3, 3):
        fx, fy, cx, cy = values[0, 0], values[1, 1], values[0, 2], values[1, 2]
    else:
        raise ValueError(
            f"intrinsics must be (fx, fy, cx, cy) in pixels or a 3x3 K, got shape {values.shape}"
        )
    if not (np.all(np.isfinite([fx, fy, cx, cy])) and fx > 0 and fy > 0):
        raise ValueError(
            f"intrinsics need finite values and fx, fy > 0, got fx={fx}, fy={fy}, cx={cx}, cy={cy}"
        )
    return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])


def crop_box(
    in_height: int, in_width: int, height: int, width: int, aspect: str
) -> tuple[int, int, int, int]:
    """(top, left, crop height, crop width) of the input that is resized to the model's
    height x width: the whole image for "resize", the centred crop of the model's aspect
    ratio for "crop"."""
    if aspect not in ASPECT_MODES:
        raise ValueError(f"aspect must be one of {ASPECT_MODES}, got {aspect!r}")
    if aspect == "resize":
        return 0, 0, in_height, in_width
    crop_width = min(in_width, max(1, round(in_height * width / height)))
    crop_height = min(in_height, max(1, round(in_width * height / width)))
    return (in_height - crop_height) // 2, (in_width - crop_width) // 2, crop_height, crop_width


def resize_camera_matrix(
    camera_matrix: np.ndarray,
    box: tuple[int, int, int, int],
    height: int,
    width: int,
) -> np.ndarray:
    """The camera of a cropped and resized image.

    Args:
      camera_matrix: [3, 3] pixel-index K of the input ((0, 0) the top-left pixel's centre).
      box: (top, left, crop height, crop width) of the input (`crop_box`).
      height, width: the size the crop is resized to.

    Returns:
      [3, 3] K of the resized crop: fx * sx and (cx - left + 0.5) * sx - 0.5 (likewise y),
      the half pixels because pixel centres, not corners, sit at integer coordinates.
    """
    top, left, crop_height, crop_width = box
    scale_x, scale_y = width / crop_width, height / crop_height
    resized = np.array(camera_matrix, np.float64)
    resized[0, 0] *= scale_x
    resized[1, 1] *= scale_y
    resized[0, 2] = (camera_matrix[0, 2] - left + 0.5) * scale_x - 0.5
    resized[1, 2] = (camera_matrix[1, 2] - top + 0.5) * scale_y - 0.5
    return resized


def _readings(ranges: Any, where: str) -> np.ndarray:
    """One pair's range readings -> [N, 3] (u, v, distance), N >= 1."""
    readings = np.asarray(ranges, np.float64)
    if readings.shape == (3,):
        readings = readings[None]
    if readings.ndim != 2 or readings.shape[1] != 3 or len(readings) == 0:
        raise ValueError(
            f"ranges{where} must be one or more (u, v, distance) readings, [N, 3], got shape "
            f"{readings.shape}"
        )
    return readings


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
        given = {keys: source for source, keys in GIVEN_POSE_INPUTS.items()}
        if extra_inputs and extra_inputs not in given and extra_inputs != CAMERA_INPUTS:
            raise ValueError(f"the model also reads {list(extra_inputs)}, which a predictor lacks")
        # "pose": the model was trained given the true relative pose (odometry here);
        # "flow_pose": the essential matrix's pose from its input flow; None: neither.
        self.given_pose = given.get(extra_inputs)
        # Models that take the motion from the flow's geometry need the camera.
        self.needs_camera = extra_inputs in (FLOW_POSE_KEYS, CAMERA_INPUTS)
        self._reads_cameras = extra_inputs == CAMERA_INPUTS
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

    def _prepare(self, images: np.ndarray, box: tuple[int, int, int, int]) -> np.ndarray:
        top, left, crop_height, crop_width = box
        return np.stack(
            [
                cv2.resize(
                    np.ascontiguousarray(image[top : top + crop_height, left : left + crop_width]),
                    (self.width, self.height),
                    interpolation=cv2.INTER_AREA,
                )
                for image in images
            ]
        )

    def _check_aspect(self, in_height: int, in_width: int) -> None:
        stretch = (self.width / in_width) / (self.height / in_height)
        if self.aspect == "resize" and abs(stretch - 1.0) > _ASPECT_TOLERANCE:
            warnings.warn(
                f"input {in_width}x{in_height} has another aspect ratio than the model's "
                f"{self.width}x{self.height}: it is stretched (x by {stretch:.3f} relative to "
                f"y), which distorts the flow the model sees; use aspect='crop' to crop instead",
                UserWarning,
                stacklevel=3,
            )

    def _scales(
        self,
        depth: np.ndarray,
        baseline: Any,
        ranges: Any,
        single: bool,
    ) -> tuple[np.ndarray, str]:
        """Metres per unit [B] and the scale's source."""
        batch_size = len(depth)
        if baseline is not None and ranges is not None:
            raise ValueError("give baseline= or ranges=, not both")
        if baseline is not None:
            scales = scale_lib.scale_from_baseline(baseline)
            if scales.ndim == 0:
                scales = np.full(batch_size, scales, np.float32)
            if scales.shape != (batch_size,):
                raise ValueError(
                    f"baseline must be one number or one per pair ([{batch_size}]), got "
                    f"shape {np.shape(baseline)}"
                )
            return scales, "baseline"
        if ranges is not None:
            per_pair = [ranges] if single else list(ranges)
            if len(per_pair) != batch_size:
                raise ValueError(
                    f"ranges must hold one [N, 3] array of readings per pair ({batch_size}), "
                    f"got {len(per_pair)}"
                )
            scales = []
            for index, (pair_depth, pair_ranges) in enumerate(zip(depth, per_pair, strict=True)):
                where = "" if single else f"[{index}]"
                readings = _readings(pair_ranges, where)
                try:
                    scales.append(
                        scale_lib.scale_from_ranges(pair_depth, readings[:, :2], readings[:, 2])
                    )
                except ValueError as error:
                    raise ValueError(f"ranges{where}: {error}") from None
            return np.asarray(scales, np.float32), "ranges"
        return np.ones(batch_size, np.float32), "none"

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
        """The model's pose inputs by keyword, and the baseline (||t|| of a given
        odometry when no other scale was given)."""
        batch_size = len(model_flow)
        if self.given_pose != "pose":
            if rotation is not None or translation is not None:
                raise ValueError(
                    "rotation= and translation= are for models trained given the relative "
                    f"pose; this one takes {self.given_pose or 'its global encoder'}'s"
                )
        if not self.needs_camera and self.given_pose is None:
            return {}, baseline
        if self.needs_camera:
            if camera_matrix is None:
                raise ValueError(
                    "the model takes the camera motion from its flow's geometry, which needs "
                    "the camera: give intrinsics="
                )
            camera = resize_camera_matrix(camera_matrix, box, self.height, self.width)
            normalised = geometry.normalised_intrinsics(camera, self.height, self.width)
            normalised = normalised.astype(np.float32)
        if self._reads_cameras:
            cameras = np.tile(normalised, (batch_size, 1))
            return {"intrinsics1": cameras, "intrinsics2": cameras}, baseline
        if self.given_pose == "flow_pose":
            poses = [flow_pose.pose_of_example(flow, normalised, normalised) for flow in model_flow]
            return {
                "flow_rotation": np.stack([pose[0] for pose in poses]),
                "flow_translation": np.stack([pose[1] for pose in poses]),
            }, baseline
        if rotation is None or translation is None:
            raise ValueError(
                "the model was trained given the relative pose (global_source pose): give "
                "the pair's odometry as rotation= [3, 3] and translation= [3] (X2 = R X1 + t)"
            )
        rotation = np.asarray(rotation, np.float32)
        translation = np.asarray(translation, np.float32)
        if single:
            rotation, translation = rotation[None], translation[None]
        if rotation.shape != (batch_size, 3, 3) or translation.shape != (batch_size, 3):
            raise ValueError(
                f"rotation and translation must be [{'' if single else 'B, '}3, 3] and "
                f"[{'' if single else 'B, '}3] for {batch_size} pair(s), got shapes "
                f"{np.shape(rotation)} and {np.shape(translation)}"
            )
        if not (np.all(np.isfinite(rotation)) and np.all(np.isfinite(translation))):
            raise ValueError("rotation or translation contains NaN or inf")
        orthonormality = np.abs(rotation @ np.swapaxes(rotation, 1, 2) - np.eye(3)).max()
        if orthonormality > 1e-3:
            raise ValueError(
                f"rotation is not a rotation matrix (R R^T is off by {orthonormality:.3g})"
            )
        norms = np.linalg.norm(translation, axis=-1)
        if np.any(norms <= 0):
            raise ValueError("translation is zero: a pair without motion has no depth")
        if baseline is None and ranges is None:
            baseline = norms if not single else float(norms[0])
        return {"rotation": rotation, "translation": translation / norms[:, None]}, baseline

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
            the pose from its flow, or refining its encoder's pose on it) needs them.
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
                f"of a pair in the same format"
            )
        batch_size, in_height, in_width, _ = first.shape
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
        box = crop_box(in_height, in_width, self.height, self.width, self.aspect)
        self._check_aspect(box[2], box[3])
        resized1, resized2 = self._prepare(first, box), self._prepare(second, box)
        if flow is None:
            model_flow = np.stack(
                [
                    trained_flow.estimate_flow(a, b, self.flow_method)
                    for a, b in zip(resized1, resized2, strict=True)
                ]
            )
        else:
            flow_scale = np.array([self.width / box[3], self.height / box[2]], np.float32)
            model_flow = self._prepare(flow, box) * flow_scale
        extra, baseline = self._given_pose(
            rotation, translation, model_flow, camera_matrix, box, single, baseline, ranges
        )
        outputs = self._apply(self.variables, resized1 - 0.5, resized2 - 0.5, model_flow, extra)
        # Per-pair arrays only: filter banks and the pose g stands for are training aids.
        outputs = jax.device_get({k: v for k, v in outputs.items() if isinstance(v, jax.Array)})
        outputs = {k: np.asarray(v) for k, v in outputs.items()}
        top, left, crop_height, crop_width = box
        depth = np.full((batch_size, in_height, in_width), np.nan, np.float32)
        for index, inv_depth in enumerate(outputs["inv_depth"]):
            resized = cv2.resize(
                inv_depth, (crop_width, crop_height), interpolation=cv2.INTER_LINEAR
            )
            depth[index, top : top + crop_height, left : left + crop_width] = 1.0 / resized
        scales, source = self._scales(depth, baseline, ranges, single)
        outputs["depth_baseline_units"] = depth
        outputs["depth"] = depth * scales[:, None, None]
        outputs["scale"] = scales
        if camera_matrix is not None:
            outputs["points"] = geometry.backproject(outputs["depth"], camera_matrix).astype(
                np.float32
            )
        if single:
            outputs = {k: v[0] for k, v in outputs.items()}
        outputs["units"] = "baseline" if source == "none" else "metres"
        outputs["scale_source"] = source
        if camera_matrix is not None:
            outputs["model_camera_matrix"] = resize_camera_matrix(
                camera_matrix, box, self.height, self.width
            )
        return outputs

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

DEPTH_FORMATS = ("png", "npy")
VIDEO_NAME_DIGITS = 6


def read_frame_file(path: str | Path) -> np.ndarray:
    """An image file as stored: [H, W] greyscale, [H, W, 3] RGB or [H, W, 4] RGBA, in its
    own dtype (the predictor's rules decide what is accepted)."""
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise ValueError(f"cannot read image {path}")
    if image.ndim == 3 and image.shape[-1] == 3:
        return cv2.cvtColor(image, cv2.COLOR_BGR2RGB)
    if image.ndim == 3 and image.shape[-1] == 4:
        return cv2.cvtColor(image, cv2.COLOR_BGRA2RGBA)
    return image


class _CachedFrames:
    """Random access to frames with the most recently used ones kept."""

    def __init__(self, names: Sequence[str], cache_size: int):
        self.names = list(names)
        self._cache: collections.OrderedDict[int, np.ndarray] = collections.OrderedDict()
        self.cache_size = max(2, cache_size)

    def __len__(self) -> int:
        return len(self.names)

    def _keep(self, index: int, frame: np.ndarray) -> None:
        self._cache[index] = frame
        self._cache.move_to_end(index)
        while len(self._cache) > self.cache_size:
            self._cache.popitem(last=False)

    def _read(self, index: int) -> np.ndarray:
        raise NotImplementedError

    def read(self, index: int) -> np.ndarray:
        if index in self._cache:
            self._cache.move_to_end(index)
            return self._cache[index]
        frame = self._read(index)
        self._keep(index, frame)
        return frame

    def close(self) -> None:
        self._cache.clear()


class ImageFolderFrames(_CachedFrames):
    """Frames from image files (in the given order), named by their file names' stems."""

    def __init__(self, paths: Sequence[str | Path], cache_size: int = 8):
        self.paths = [Path(path) for path in paths]
        if not self.paths:
            raise ValueError("no image files given")
        super().__init__([path.stem for path in self.paths], cache_size)

    def _read(self, index: int) -> np.ndarray:
        return read_frame_file(self.paths[index])


class VideoFrames(_CachedFrames):
    """Frames of a video file (OpenCV), named by their index (000000, 000001, ...).

    Frames are decoded in order; those decoded on the way to a later frame stay in the
    cache, so pairs taken in recording order decode each frame once. An earlier frame
    that has left the cache is reached by seeking.
    """

    def __init__(self, path: str | Path, cache_size: int = 8):
        self.path = Path(path)
        if not self.path.is_file():
            raise FileNotFoundError(f"video {self.path} does not exist")
        self._capture = cv2.VideoCapture(str(self.path))
        if not self._capture.isOpened():
            raise ValueError(f"cannot open video {self.path} with OpenCV")
        count = int(self._capture.get(cv2.CAP_PROP_FRAME_COUNT))
        if count <= 0:
            raise ValueError(f"video {self.path}: OpenCV reports no frames")
        self._position = 0
        super().__init__([f"{i:0{VIDEO_NAME_DIGITS}d}" for i in range(count)], cache_size)

    def _read(self, index: int) -> np.ndarray:
        if index < self._position or index - self._position > self.cache_size:
            self._capture.set(cv2.CAP_PROP_POS_FRAMES, index)
            self._position = index
        while True:
            ok, frame = self._capture.read()
            if not ok:
                raise ValueError(
                    f"video {self.path}: cannot decode frame {self._position} (the file "
                    f"reports {len(self.names)} frames)"
                )
            frame = cv2.cvtColor(frame, cv2.COLOR_BGR2RGB)
            self._position += 1
            if self._position - 1 == index:
                return frame
            self._keep(self._position - 1, frame)

    def close(self) -> None:
        super().close()
        self._capture.release()


def frame_pairs(count: int, frame_gap: int = 1) -> list[tuple[int, int]]:
    """(i, i + frame_gap) for every frame i that has a partner."""
    if frame_gap < 1:
        raise ValueError(f"frame_gap must be >= 1, got {frame_gap}")
    if count <= frame_gap:
        raise ValueError(f"{count} frame(s) make no pair at frame gap {frame_gap}")
    return [(i, i + frame_gap) for i in range(count - frame_gap)]


def _frame_index(frame: str, index_of: dict[str, int], count: int) -> int | None:
    """A frame named by its name (file stem) or by its index in order."""
    if frame in index_of:
        return index_of[frame]
    if frame.isdigit() and int(frame) < count:
        return int(frame)
    return None


def read_pairs_file(path: str | Path, names: Sequence[str]) -> list[tuple[int, int]]:
    """A text file of pairs, one `frame1 frame2` per line (comma or space separated, `#`
    comments), frames by name (file stem) or index -> [(i, j)].

    Raises:
      FileNotFoundError / ValueError naming the file and line.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"pairs file {path} does not exist")
    index_of = {name: index for index, name in enumerate(names)}
    pairs = []
    for line_number, line in enumerate(path.read_text().splitlines(), 1):
        fields = line.split("#", 1)[0].replace(",", " ").split()
        if not fields:
            continue
        if len(fields) != 2:
            raise ValueError(f"{path}:{line_number}: expected 'frame1 frame2', got {line!r}")
        indices = [_frame_index(field, index_of, len(names)) for field in fields]
        for field, index in zip(fields, indices, strict=True):
            if index is None:
                raise ValueError(f"{path}:{line_number}: frame {field!r} is not a frame")
        if indices[0] == indices[1]:
            raise ValueError(f"{path}:{line_number}: a frame cannot pair with itself")
        pairs.append((indices[0], indices[1]))
    if not pairs:
        raise ValueError(f"{path}: no pairs")
    return pairs


def read_range_readings(
    path: str | Path,
    names: Sequence[str],
    image_size: tuple[int, int],
    depth_scale: float = 1.0,
) -> dict[int, np.ndarray]:
    """Range readings of the CSV format of `data.demon.convert`: `frame,u,v,depth`.

    `frame` is a frame's name (file stem) or its index in order; u, v are pixels of the
    image ((0, 0) the top-left pixel's centre); depth times `depth_scale` is camera-z
    metres. A header line and `#` comments are skipped; readings whose depth is not
    finite or not positive (a sensor's "no return") are dropped, as the converter does.

    Returns:
      frame index -> [N, 3] float64 (u, v, metres).

    Raises:
      FileNotFoundError / ValueError naming the file and line: a row that is not
      four fields, not numbers, of an unknown frame, or a pixel outside the image.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"range readings {path} do not exist")
    height, width = image_size
    index_of = {name: index for index, name in enumerate(names)}
    readings: dict[int, list[tuple[float, float, float]]] = collections.defaultdict(list)
    with path.open(newline="") as stream:
        for line_number, row in enumerate(csv.reader(stream), 1):
            if not row or not "".join(row).strip() or row[0].strip().startswith("#"):
                continue
            if len(row) != 4:
                raise ValueError(f"{path}:{line_number}: expected frame,u,v,depth, got {row}")
            try:
                u, v, depth = (float(value) for value in row[1:])
            except ValueError:
                if line_number == 1:
                    continue  # header
                raise ValueError(f"{path}:{line_number}: not numbers: {row}") from None
            frame = row[0].strip()
            index = _frame_index(frame, index_of, len(names))
            if index is None:
                raise ValueError(f"{path}:{line_number}: frame {frame!r} is not a frame")
            if not (np.isfinite(u) and np.isfinite(v)) or not (
                -0.5 <= u <= width - 0.5 and -0.5 <= v <= height - 0.5
            ):
                raise ValueError(
                    f"{path}:{line_number}: pixel ({u}, {v}) outside the {width}x{height} image"
                )
            if np.isfinite(depth) and depth > 0:
                readings[index].append((u, v, depth * depth_scale))
    return {index: np.asarray(rows, np.float64) for index, rows in readings.items()}


@dataclasses.dataclass
class RecordingPlan:
    """The pairs to predict, each with its scale's measurement, and those skipped."""

    pairs: list[tuple[int, int]]
    scale_source: str  # "ranges", "baseline" or "none"
    ranges: list[np.ndarray] | None = None
    baselines: list[float] | None = None
    skipped: dict[str, int] = dataclasses.field(default_factory=dict)
    # Each pair's relative pose (rotation [3, 3], translation [3] in metres), when the
    # plan was made from full camera poses.
    motions: list[tuple[np.ndarray, np.ndarray]] | None = None


def relative_motion(
    camera_to_world1: np.ndarray, camera_to_world2: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """The relative pose of a pair from two camera-to-world poses ([4, 4] or [3, 4],
    OpenCV camera axes): rotation [3, 3] and translation [3] with X2 = R X1 + t."""
    poses = []
    for pose in (camera_to_world1, camera_to_world2):
        pose = np.asarray(pose, np.float64)
        if pose.shape not in ((4, 4), (3, 4)):
            raise ValueError(f"a camera pose must be [4, 4] or [3, 4], got shape {pose.shape}")
        world_to_camera = pose[:3, :3].T
        poses.append((world_to_camera, -world_to_camera @ pose[:3, 3]))
    return geometry.relative_pose(*poses[0], *poses[1])


def plan_recording(
    pairs: Sequence[tuple[int, int]],
    *,
    ranges: dict[int, np.ndarray] | None = None,
    positions: np.ndarray | None = None,
    camera_to_world: np.ndarray | None = None,
    min_baseline: float = 0.0,
) -> RecordingPlan:
    """Attaches each pair's scale measurement and drops the pairs that have none.

    Args:
      pairs: (i, j) frame indices; depth is predicted for frame i.
      ranges: frame index -> [N, 3] readings (`read_range_readings`); a pair uses those
        of its first frame.
      positions: [F, 3] camera centres of every frame, metres; a pair's baseline is the
        distance between its frames'.
      camera_to_world: [F, 4, 4] camera poses of every frame (metres), instead of
        positions: the baseline as from their centres, and each pair's relative pose
        (`relative_motion`) for a model trained given it.
      min_baseline: pairs whose baseline is not above this are skipped.

    Raises:
      ValueError: when both sources are given, or when no pair keeps a measurement.
    """
    if sum(source is not None for source in (ranges, positions, camera_to_world)) > 1:
        raise ValueError("give one of range readings, camera positions or camera poses")
    pairs = list(pairs)
    if camera_to_world is not None:
        camera_to_world = np.asarray(camera_to_world, np.float64)
        positions = camera_to_world[:, :3, 3]
    if ranges is not None:
        kept = [pair for pair in pairs if pair[0] in ranges]
        plan = RecordingPlan(kept, "ranges", ranges=[ranges[i] for i, _ in kept])
        plan.skipped = {"no range reading on the first frame": len(pairs) - len(kept)}
    elif positions is not None:
        positions = np.asarray(positions, np.float64)
        baselines = [float(np.linalg.norm(positions[j] - positions[i])) for i, j in pairs]
        keep = [b > min_baseline and np.isfinite(b) for b in baselines]
        plan = RecordingPlan(
            [pair for pair, ok in zip(pairs, keep, strict=True) if ok],
            "baseline",
            baselines=[b for b, ok in zip(baselines, keep, strict=True) if ok],
        )
        plan.skipped = {f"baseline <= {min_baseline} m": len(pairs) - len(plan.pairs)}
        if camera_to_world is not None:
            plan.motions = [
                relative_motion(camera_to_world[i], camera_to_world[j]) for i, j in plan.pairs
            ]
    else:
        plan = RecordingPlan(pairs, "none")
    if not plan.pairs:
        reasons = ", ".join(f"{count} {reason}" for reason, count in plan.skipped.items())
        raise ValueError(f"no pair left to predict ({reasons})")
    return plan


def pair_name(names: Sequence[str], pair: tuple[int, int]) -> str:
    return f"{names[pair[0]]}__{names[pair[1]]}"


def predict_recording(
    predictor,
    frames: _CachedFrames,
    plan: RecordingPlan,
    out_dir: str | Path,
    *,
    batch_size: int = 8,
    depth_format: str = "png",
    previews: bool = False,
    camera_matrix: np.ndarray | None = None,
    ply: bool = False,
    progress: Callable[[int], None] | None = None,
) -> dict[str, Any]:
    """Predicts depth for every planned pair in batches and writes it (module docstring).

    Every batch has `batch_size` pairs (the last one padded by repeating its last pair),
    so the model is compiled once.

    Args:
      predictor: a `gld.inference.predict.DepthPredictor`.
      frames: the recording's frames (`ImageFolderFrames`, `VideoFrames`).
      plan: the pairs and their scale measurements (`plan_recording`).
      out_dir: the output folder (created).
      batch_size: pairs per model call.
      depth_format: "png" (16-bit millimetres; needs metric depth) or "npy".
      previews: also write colour previews.
      camera_matrix: [3, 3] K of the frames (pixels), for point clouds.
      ply: write a PLY point cloud per pair (needs camera_matrix).
      progress: called with the number of pairs done after each batch.

    Returns:
      The summary written to summary.json.
    """
    if depth_format not in DEPTH_FORMATS:
        raise ValueError(f"depth format must be one of {DEPTH_FORMATS}, got {depth_format!r}")
    if depth_format == "png" and plan.scale_source == "none":
        raise ValueError(
            "16-bit PNG depth is millimetres and needs metric depth: give range readings or "
            "camera positions, or write .npy"
        )
    if ply and camera_matrix is None:
        raise ValueError("point clouds need the camera's intrinsics")
    if batch_size < 1:
        raise ValueError(f"batch_size must be >= 1, got {batch_size}")
    first = plan.pairs[0][0]
    check_image(frames.read(first), f"frame {frames.names[first]}")
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    units = "baseline" if plan.scale_source == "none" else "metres"
    unstored_pixels = 0
    with (out_dir / "pairs.csv").open("w", newline="") as stream:
        writer = csv.writer(stream)
        writer.writerow(["pair", "frame1", "frame2", "scale", "scale_source", "units", "depth"])
        for start in range(0, len(plan.pairs), batch_size):
            indices = list(range(start, min(start + batch_size, len(plan.pairs))))
            padded = indices + [indices[-1]] * (batch_size - len(indices))
            images1 = [frames.read(plan.pairs[k][0]) for k in padded]
            images2 = [frames.read(plan.pairs[k][1]) for k in padded]
            shapes = {image.shape for image in images1 + images2}
            if len(shapes) != 1:
                names = [pair_name(frames.names, plan.pairs[k]) for k in indices]
                raise ValueError(f"frames of different sizes {sorted(shapes)} in pairs {names}")
            options: dict[str, Any] = {}
            if plan.scale_source == "ranges":
                options["ranges"] = [plan.ranges[k] for k in padded]
            elif plan.scale_source == "baseline":
                options["baseline"] = np.array([plan.baselines[k] for k in padded])
            if getattr(predictor, "given_pose", None) == "pose":
                if plan.motions is None:
                    raise ValueError(
                        "the model was trained given the relative pose: plan the recording "
                        "with camera poses (camera_to_world=, --poses) to give it the odometry"
                    )
                options["rotation"] = np.stack([plan.motions[k][0] for k in padded])
                options["translation"] = np.stack([plan.motions[k][1] for k in padded])
            if getattr(predictor, "needs_camera", False):
                if camera_matrix is None:
                    raise ValueError(
                        "the model takes the camera motion from its flow: give the camera's "
                        "intrinsics"
                    )
                options["intrinsics"] = camera_matrix
            try:
                outputs = predictor.predict(np.stack(images1), np.stack(images2), **options)
            except ValueError as error:
                names = [pair_name(frames.names, plan.pairs[k]) for k in indices]
                raise ValueError(f"pairs {names[0]} .. {names[-1]}: {error}") from None
            for position, k in enumerate(indices):
                name = pair_name(frames.names, plan.pairs[k])
                depth = outputs["depth"][position]
                depth_path = out_dir / "depth" / f"{name}.{depth_format}"
                if depth_format == "png":
                    unstored_pixels += depth_io.write_depth_png(depth_path, depth)
                else:
                    depth_io.write_depth_npy(depth_path, depth)
                colour_image = _display_image(images1[position])
                if previews:
                    depth_io.write_preview(out_dir / "preview" / f"{name}.png", colour_image, depth)
                if ply:
                    points, colours = depth_io.point_cloud(depth, camera_matrix, colour_image)
                    depth_io.write_ply(out_dir / "ply" / f"{name}.ply", points, colours)
                first, second = plan.pairs[k]
                writer.writerow(
                    [
                        name,
                        frames.names[first],
                        frames.names[second],
                        f"{float(outputs['scale'][position]):.6g}",
                        plan.scale_source,
                        units,
                        depth_path.relative_to(out_dir).as_posix(),
                    ]
                )
            stream.flush()
            if progress is not None:
                progress(len(indices))
    summary = {
        "pairs_written": len(plan.pairs),
        "pairs_skipped": plan.skipped,
        "scale_source": plan.scale_source,
        "units": units,
        "depth_format": depth_format,
        "png_depth_scale": depth_io.PNG_DEPTH_SCALE if depth_format == "png" else None,
        "png_unstored_pixels": unstored_pixels if depth_format == "png" else None,
        "previews": previews,
        "ply": ply,
        "camera_matrix": None if camera_matrix is None else np.asarray(camera_matrix).tolist(),
        "model_resolution": [predictor.height, predictor.width],
        "aspect": predictor.aspect,
    }
    (out_dir / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")
    return summary


def _display_image(image: np.ndarray) -> np.ndarray:
    """A frame as [H, W, 3] uint8 RGB for previews and point colours."""
    image = np.asarray(image)
    if image.dtype != np.uint8:
        image = np.clip(image.astype(np.float64) * 255.0 + 0.5, 0, 255).astype(np.uint8)
    if image.ndim == 2:
        image = image[..., None]
    if image.shape[-1] == 1:
        image = np.repeat(image, 3, axis=-1)
    return image[..., :3]
