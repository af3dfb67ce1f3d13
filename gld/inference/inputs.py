"""What a predictor accepts: images, cameras, range readings; crop and resize.

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
"""

from __future__ import annotations

import dataclasses
import warnings
from typing import Any

import numpy as np

from gld import flow_pose, geometry

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


def odometry(
    rotation: Any, translation: Any, batch_size: int, single: bool
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A pair's (or batch's) relative pose from odometry, checked: X2 = R X1 + t.

    Args:
      rotation, translation: [3, 3] and [3] for one pair (`single`), [B, 3, 3] and [B, 3]
        for a batch of `batch_size`.

    Returns:
      ([B, 3, 3] rotation, [B, 3] unit translation (the model's ||t|| = 1), [B] ||t||),
      float32.
    """
    rotation = np.asarray(rotation, np.float32)
    translation = np.asarray(translation, np.float32)
    if single:
        rotation, translation = rotation[None], translation[None]
    if rotation.shape != (batch_size, 3, 3) or translation.shape != (batch_size, 3):
        raise ValueError(
            f"rotation and translation must be [{'' if single else 'B, '}3, 3] and "
            f"[{'' if single else 'B, '}3] for {batch_size} pair(s), got shapes "
            f"{np.shape(rotation)[1 if single else 0 :]} and "
            f"{np.shape(translation)[1 if single else 0 :]}"
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
    return rotation, translation / norms[:, None], norms


def warn_if_stretched(
    box: tuple[int, int, int, int], height: int, width: int, aspect: str, stacklevel: int
) -> None:
    """A `UserWarning` when aspect "resize" stretches the input's `box` (`crop_box`) of
    another aspect ratio to the model's height x width."""
    crop_height, crop_width = box[2], box[3]
    stretch = (width / crop_width) / (height / crop_height)
    if aspect == "resize" and abs(stretch - 1.0) > _ASPECT_TOLERANCE:
        warnings.warn(
            f"input {crop_width}x{crop_height} has another aspect ratio than the model's "
            f"{width}x{height}: it is stretched (x by {stretch:.3f} relative to y), which "
            "distorts the flow the model sees; use aspect='crop' to crop instead",
            UserWarning,
            stacklevel=stacklevel + 1,
        )


# The keyword inputs a model may read besides the images and flow
# (`GlobalLocal.extra_inputs`): the odometry's relative pose, the essential matrix's pose
# from its flow, the cameras (named here: the runtime does not import the models).
ODOMETRY_INPUTS = ("rotation", "translation")
CAMERA_INPUTS = ("intrinsics1", "intrinsics2")


@dataclasses.dataclass(frozen=True)
class PoseInputs:
    """What a model reads besides the images and flow: a given pose (the odometry's or
    its flow's essential matrix's, not both), the cameras, or a given pose and the
    cameras (a model that reads it against the flow)."""

    odometry: bool
    flow_pose: bool
    cameras: bool

    @property
    def needs_camera(self) -> bool:
        """Whether a call needs intrinsics= (the essential matrix, or the cameras)."""
        return self.flow_pose or self.cameras

    @classmethod
    def of(cls, extra_inputs: Any, refusal: str) -> PoseInputs:
        """What `extra_inputs` (a model's keys) ask for; ValueError "the model reads
        [...], which <refusal>" for any other key, half a pose or two poses."""
        extra = tuple(extra_inputs)
        reads = cls(
            odometry=set(ODOMETRY_INPUTS) <= set(extra),
            flow_pose=set(flow_pose.FLOW_POSE_KEYS) <= set(extra),
            cameras=set(CAMERA_INPUTS) <= set(extra),
        )
        known = (
            set(ODOMETRY_INPUTS if reads.odometry else ())
            | set(flow_pose.FLOW_POSE_KEYS if reads.flow_pose else ())
            | set(CAMERA_INPUTS if reads.cameras else ())
        )
        if (
            len(set(extra)) != len(extra)
            or set(extra) != known
            or (reads.odometry and reads.flow_pose)
        ):
            raise ValueError(f"the model reads {list(extra)}, which {refusal}")
        return reads

    def keywords(
        self,
        flow: np.ndarray,
        camera_matrix: np.ndarray | None,
        rotation: Any,
        translation: Any,
        single: bool,
    ) -> tuple[dict[str, np.ndarray], np.ndarray | None]:
        """The model's keyword inputs for a batch, and ||t|| of the odometry (None without).

        Args:
          flow: [B, h, w, 2] the model's flow, at its resolution.
          camera_matrix: [3, 3] pixel-index K at the model's resolution, or None.
          rotation, translation: the odometry (`odometry`), or None.
          single: the odometry is one pair's, without the batch axis.
        """
        batch_size, height, width = flow.shape[:3]
        if not self.odometry and (rotation is not None or translation is not None):
            raise ValueError(
                "rotation= and translation= are for models trained given the relative pose; "
                "this one takes the motion from the images"
            )
        keywords: dict[str, np.ndarray] = {}
        norms = None
        if self.odometry:
            if rotation is None or translation is None:
                raise ValueError(
                    "the model was trained given the relative pose: give the pair's odometry "
                    "as rotation= [3, 3] and translation= [3] (X2 = R X1 + t)"
                )
            rotation, unit, norms = odometry(rotation, translation, batch_size, single)
            keywords.update(rotation=rotation, translation=unit)
        if not self.needs_camera:
            return keywords, norms
        if camera_matrix is None:
            raise ValueError(
                "the model takes the camera motion from its flow's geometry, which needs the "
                "camera: give intrinsics="
            )
        normalised = np.asarray(
            geometry.normalised_intrinsics(camera_matrix, height, width), np.float32
        )
        if self.flow_pose:
            poses = flow_pose.in_parallel(
                flow_pose.pose_of_example, [(pair, normalised, normalised) for pair in flow]
            )
            keywords.update(
                flow_rotation=np.stack([pose[0] for pose in poses]).astype(np.float32),
                flow_translation=np.stack([pose[1] for pose in poses]).astype(np.float32),
            )
        if self.cameras:
            cameras = np.tile(normalised, (batch_size, 1))
            keywords.update(intrinsics1=cameras, intrinsics2=cameras)
        return keywords, norms
