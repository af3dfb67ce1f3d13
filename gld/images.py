"""Images in gld's contract: RGB float32 in [-0.5, 0.5], [H, W, 3].

image = as_unit_rgb(frame, "image1")   # uint8 or float RGB, or greyscale
"""

from __future__ import annotations

import numpy as np


def as_unit_rgb(image: np.ndarray, name: str) -> np.ndarray:
    """[H, W, 3] float32 in gld's image contract ([-0.5, 0.5]) from uint8 or float
    ([-0.5, 0.5] or [0, 1]) RGB, or from [H, W] greyscale (replicated)."""
    image = np.asarray(image)
    if image.ndim == 2:
        image = np.repeat(image[..., None], 3, axis=-1)
    if image.ndim != 3 or image.shape[-1] != 3:
        raise ValueError(f"{name} must be [H, W] or [H, W, 3], got shape {image.shape}")
    if image.dtype == np.uint8:
        return image.astype(np.float32) / 255.0 - 0.5
    if not np.issubdtype(image.dtype, np.floating):
        raise ValueError(f"{name} must be uint8 or float, got dtype {image.dtype}")
    if not np.all(np.isfinite(image)):
        raise ValueError(f"{name} contains NaN or inf")
    offset = 0.0 if image.min() < 0 else 0.5
    return (image - offset).astype(np.float32)
