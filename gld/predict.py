"""Depth from two images with a trained model: the Python API for inference.

    from gld.predict import DepthPredictor
    predictor = DepthPredictor.from_workdir("runs/demo")
    depth = predictor(image1, image2)          # [H, W], at the input size

Images may be uint8 (0..255) or float in [0, 1], any size, single pairs [H, W, 3] or
batches [B, H, W, 3]. They are resized to the resolution the model was trained at;
flow is computed there with the default estimator (OpenCV DIS) unless given, and the
predicted depth is resized back to the input size. Depth is in the training scale:
units of the pair's baseline (||t|| = 1).
"""

from __future__ import annotations

from pathlib import Path

import cv2
import jax
import numpy as np

from gld import flow as flow_lib
from gld import workdir as workdir_lib


def _as_float_images(image: np.ndarray, name: str) -> np.ndarray:
    image = np.asarray(image)
    if image.ndim not in (3, 4) or image.shape[-1] != 3:
        raise ValueError(f"{name} must be [H, W, 3] or [B, H, W, 3], got shape {image.shape}")
    if image.dtype == np.uint8:
        return image.astype(np.float32) / 255.0
    if not np.issubdtype(image.dtype, np.floating):
        raise ValueError(f"{name} must be uint8 or float in [0, 1], got dtype {image.dtype}")
    if not np.all(np.isfinite(image)):
        raise ValueError(f"{name} contains NaN or inf")
    if image.min() < 0.0 or image.max() > 1.0:
        raise ValueError(
            f"float {name} must lie in [0, 1], got [{image.min():.3g}, {image.max():.3g}]"
        )
    return image.astype(np.float32)


class DepthPredictor:
    """A trained depth model with jit-compiled batched inference."""

    def __init__(self, model, variables, height: int, width: int, flow_method: str = "dis"):
        self.model, self.variables = model, variables
        self.height, self.width = height, width
        self.flow_method = flow_method
        self._apply = jax.jit(
            lambda variables, image1, image2, flow: model.apply(variables, image1, image2, flow)
        )

    @classmethod
    def from_workdir(cls, workdir: str | Path, step: int | None = None) -> DepthPredictor:
        """Loads the latest (or given) checkpoint of a training workdir."""
        model, variables, config = workdir_lib.load_trained(workdir, step=step)
        return cls(model, variables, config.height, config.width)

    def predict(
        self, image1: np.ndarray, image2: np.ndarray, flow: np.ndarray | None = None
    ) -> dict[str, np.ndarray]:
        """Full model outputs at the model's resolution, plus depth at the input size.

        Args:
          image1, image2: [H, W, 3] or [B, H, W, 3], uint8 or float in [0, 1].
          flow: optional [H, W, 2] / [B, H, W, 2] flow I1 -> I2 in pixels of the input size.

        Returns:
          {"depth": depth at the input size, "inv_depth", "global_params", ...} as numpy.
        """
        first = _as_float_images(image1, "image1")
        second = _as_float_images(image2, "image2")
        if first.shape != second.shape:
            raise ValueError(
                f"image1 and image2 must have the same shape, got {first.shape} and {second.shape}"
            )
        single = first.ndim == 3
        if single:
            first, second = first[None], second[None]
            flow = None if flow is None else np.asarray(flow)[None]
        batch_size, in_height, in_width, _ = first.shape
        if flow is not None:
            flow = np.asarray(flow, np.float32)
            if flow.shape != (batch_size, in_height, in_width, 2):
                raise ValueError(
                    f"flow must be [{'' if single else 'B, '}H, W, 2] matching the images "
                    f"({in_height}x{in_width}), got shape {np.shape(flow)[1 if single else 0 :]}"
                )
        size = (self.width, self.height)
        resized1 = np.stack([cv2.resize(im, size, interpolation=cv2.INTER_AREA) for im in first])
        resized2 = np.stack([cv2.resize(im, size, interpolation=cv2.INTER_AREA) for im in second])
        if flow is None:
            model_flow = np.stack(
                [
                    flow_lib.estimate(a, b, self.flow_method)
                    for a, b in zip(resized1, resized2, strict=True)
                ]
            )
        else:
            scale = np.array([self.width / in_width, self.height / in_height], np.float32)
            model_flow = np.stack([cv2.resize(f, size) for f in flow]) * scale
        outputs = self._apply(self.variables, resized1 - 0.5, resized2 - 0.5, model_flow)
        outputs = jax.device_get({k: v for k, v in outputs.items() if k != "filter_banks"})
        inv_depth = np.stack(
            [
                cv2.resize(z, (in_width, in_height), interpolation=cv2.INTER_LINEAR)
                for z in np.asarray(outputs["inv_depth"])
            ]
        )
        outputs["depth"] = 1.0 / inv_depth
        if single:
            outputs = {k: v[0] for k, v in outputs.items()}
        return outputs

    def __call__(
        self, image1: np.ndarray, image2: np.ndarray, flow: np.ndarray | None = None
    ) -> np.ndarray:
        """Depth of view 1 at the input size: [H, W] or [B, H, W]."""
        return self.predict(image1, image2, flow)["depth"]
