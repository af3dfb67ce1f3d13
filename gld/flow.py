"""Optical-flow estimators behind one signature: `estimate(image1, image2) -> [H, W, 2]`.

Flow is in pixels, I1 -> I2: pixel p of image 1 sits at p + flow(p) in image 2.
The default, OpenCV's DIS, is used off the shelf (neither trained nor tuned on
gld's data), as the paper uses a pre-trained flow network. A flow network trained
by `experiments.train_flow` is selected as "flow_net:<its workdir>" (its newest
intact checkpoint; JAX is imported on first use and the network runs in the calling
process). Flow is computed once, when a dataset is built, and stored with the records.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from gld import geometry

DEFAULT_ESTIMATOR = "dis"


def opencv() -> Any:
    """The `cv2` module, imported on first use: the exported runtime imports this module
    where OpenCV may be absent (a model on a flow network's flow needs none)."""
    try:
        import cv2
    except ImportError as error:
        raise ImportError(
            f"OpenCV is needed for classical flow and the essential matrix ({error}): "
            "pip install opencv-python-headless"
        ) from error
    return cv2


def _as_gray_uint8(image: np.ndarray, name: str) -> np.ndarray:
    image = np.asarray(image)
    if image.ndim not in (2, 3) or (image.ndim == 3 and image.shape[-1] not in (1, 3)):
        raise ValueError(f"{name} must be [H, W] or [H, W, 3], got shape {image.shape}")
    if image.dtype != np.uint8:
        if not np.issubdtype(image.dtype, np.floating):
            raise ValueError(f"{name} must be uint8 or float, got dtype {image.dtype}")
        if not np.all(np.isfinite(image)):
            raise ValueError(f"{name} contains NaN or inf")
        # Floats follow the example contract ([-0.5, 0.5]) or [0, 1].
        offset = 0.5 if image.min() < 0 else 0.0
        image = np.clip((image + offset) * 255.0 + 0.5, 0, 255).astype(np.uint8)
    if image.ndim == 3 and image.shape[-1] == 3:
        cv2 = opencv()
        return cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)
    return image.reshape(image.shape[:2])


def _check_pair(image1: np.ndarray, image2: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    gray1 = _as_gray_uint8(image1, "image1")
    gray2 = _as_gray_uint8(image2, "image2")
    if gray1.shape != gray2.shape:
        raise ValueError(
            f"image1 and image2 must have the same size, got {np.shape(image1)} and "
            f"{np.shape(image2)}"
        )
    return gray1, gray2


def dis_flow(image1: np.ndarray, image2: np.ndarray, preset: str = "medium") -> np.ndarray:
    """OpenCV DIS optical flow (Kroeger et al. 2016) with variational refinement.

    Args:
      image1, image2: [H, W, 3] RGB (uint8, or float in [-0.5, 0.5] / [0, 1]) or [H, W].
      preset: "ultrafast", "fast" or "medium".

    Returns:
      [H, W, 2] float32 flow in pixels, I1 -> I2.
    """
    gray1, gray2 = _check_pair(image1, image2)
    cv2 = opencv()
    presets = {
        "ultrafast": cv2.DISOPTICAL_FLOW_PRESET_ULTRAFAST,
        "fast": cv2.DISOPTICAL_FLOW_PRESET_FAST,
        "medium": cv2.DISOPTICAL_FLOW_PRESET_MEDIUM,
    }
    if preset not in presets:
        raise ValueError(f"unknown DIS preset {preset!r}; valid: {sorted(presets)}")
    estimator = cv2.DISOpticalFlow_create(presets[preset])
    return estimator.calc(gray1, gray2, None).astype(np.float32)


def farneback_flow(image1: np.ndarray, image2: np.ndarray) -> np.ndarray:
    """OpenCV Farneback dense optical flow; same signature as `dis_flow`."""
    gray1, gray2 = _check_pair(image1, image2)
    cv2 = opencv()
    flow = cv2.calcOpticalFlowFarneback(
        gray1,
        gray2,
        None,
        pyr_scale=0.5,
        levels=5,
        winsize=15,
        iterations=5,
        poly_n=7,
        poly_sigma=1.5,
        flags=cv2.OPTFLOW_FARNEBACK_GAUSSIAN,
    )
    return flow.astype(np.float32)


def geometric_flow(
    depth: np.ndarray,
    intrinsics1: np.ndarray,
    intrinsics2: np.ndarray,
    rotation: np.ndarray,
    translation: np.ndarray,
    depth2: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Exact flow from view-1 depth, both normalised intrinsics and the relative pose.

    Returns flow [H, W, 2] float32 and its validity [H, W] (see
    `geometry.ground_truth_flow`).
    """
    return geometry.ground_truth_flow(
        depth, depth2, intrinsics1, intrinsics2, rotation, translation
    )


# Image-based estimators, selectable by name (the builders' `flow_estimator` setting).
ESTIMATORS: dict[str, Callable[[np.ndarray, np.ndarray], np.ndarray]] = {
    "dis": dis_flow,
    "dis_fast": lambda image1, image2: dis_flow(image1, image2, preset="fast"),
    "farneback": farneback_flow,
}


# A trained flow network: "flow_net:<workdir of experiments.train_flow>".
LEARNED_PREFIX = "flow_net:"
# The file a flow network's run stores its config in, which marks its workdir
# (written by `gld.training.flow_trainer`, read by `gld.runs.flow_config`).
FLOW_CONFIG_FILE = "flow_config.json"


# How each classical estimator sees the frames and calls OpenCV, recorded in an exported
# model's metadata ("flow") and checked by its runtime (`gld.inference.runtime`), which
# runs the same `estimate` on the frames resized to the model's resolution.
_GREYSCALE = "uint8 greyscale: cv2.cvtColor(RGB2GRAY) of round(255 x image), image in [0, 1]"
RUNTIME_SETTINGS: dict[str, dict[str, Any]] = {
    "dis": {"opencv": "DISOpticalFlow", "preset": "medium", "input": _GREYSCALE},
    "dis_fast": {"opencv": "DISOpticalFlow", "preset": "fast", "input": _GREYSCALE},
    "farneback": {
        "opencv": "calcOpticalFlowFarneback",
        "parameters": "pyr_scale=0.5 levels=5 winsize=15 iterations=5 poly_n=7 "
        "poly_sigma=1.5 flags=OPTFLOW_FARNEBACK_GAUSSIAN",
        "input": _GREYSCALE,
    },
}


def runtime_settings(method: str) -> dict[str, Any]:
    """{"estimator": method, ...} of a classical estimator: what a runtime must run."""
    _check_classical(method)
    return {"estimator": method, **RUNTIME_SETTINGS[method]}


def is_learned(method: str) -> bool:
    """Whether `method` names a trained flow network rather than a classical estimator."""
    return method.startswith(LEARNED_PREFIX)


def check_estimator(method: str) -> None:
    """Raises ValueError unless `method` is an `ESTIMATORS` name or "flow_net:<workdir>"
    of a flow network's run (checked before anything is built)."""
    if method in ESTIMATORS:
        return
    if is_learned(method):
        workdir = Path(method[len(LEARNED_PREFIX) :]).expanduser()
        if not (workdir / FLOW_CONFIG_FILE).is_file():
            raise ValueError(
                f"flow estimator {method!r}: {workdir} holds no flow-network run (no "
                f"{FLOW_CONFIG_FILE}); train one with python -m experiments.train_flow"
            )
        return
    raise ValueError(
        f"unknown flow estimator {method!r}; valid: {sorted(ESTIMATORS)} or "
        f"'{LEARNED_PREFIX}<workdir of a trained flow network>'"
    )


def describe(method: str) -> dict[str, Any]:
    """What produced a flow, for a dataset's card: {"estimator": method} of a classical
    estimator (a trained network's card is `gld.runs.trained_flow.describe_flow`'s)."""
    _check_classical(method)
    return {"estimator": method}


def estimate(image1: np.ndarray, image2: np.ndarray, method: str = DEFAULT_ESTIMATOR) -> np.ndarray:
    """Flow I1 -> I2 [H, W, 2] float32 with a classical estimator of `ESTIMATORS` (a trained
    network, "flow_net:<workdir>", runs through `gld.runs.trained_flow.estimate_flow`)."""
    _check_classical(method)
    return ESTIMATORS[method](image1, image2)


def _check_classical(method: str) -> None:
    check_estimator(method)
    if is_learned(method):
        raise ValueError(
            f"flow estimator {method!r} is a trained network: estimate with "
            "gld.runs.trained_flow.estimate_flow"
        )


def endpoint_error(flow: np.ndarray, flow_true: np.ndarray, valid: np.ndarray) -> float:
    """Mean end-point error in pixels over `valid` pixels ([H, W, 2], [H, W, 2], [H, W])."""
    valid = np.asarray(valid, bool)
    if not valid.any():
        return float("nan")
    return float(np.linalg.norm(flow - flow_true, axis=-1)[valid].mean())
