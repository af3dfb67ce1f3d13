"""What the hypernetwork does: global parameters, generated filter banks, and how the
similarity of two pairs' filters relates to the similarity of their camera motions."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import flax.linen as nn
import numpy as np

from gld import geometry
from gld.evaluation import reports
from gld.models import layers
from gld.models.global_local import GlobalLocal


def filter_banks(
    variables: dict, batch: dict[str, np.ndarray], model: nn.Module | None = None
) -> dict[str, object]:
    """Global parameters and generated filter banks of every pair of a batch.

    Args:
      variables: the model's variables ({"params": ...}).
      batch: "image1", "image2" [B, H, W, 3] (contract range) and "flow" [B, H, W, 2].
      model: the global-local model (default: the paper's architecture).

    Returns:
      {"global_params": [B, G], "kernels": list of [B, k, k, C_in, C_out],
       "biases": list of [B, C_out]}, numpy.
    """
    if model is None:
        model = GlobalLocal()
    outputs = layers.apply_model(model, variables, batch)
    banks = outputs["filter_banks"]
    return {
        "global_params": np.asarray(outputs["global_params"]),
        "kernels": [np.asarray(bank.kernel) for bank in banks],
        "biases": [np.asarray(bank.bias) for bank in banks],
    }


def _cosine_matrix(vectors: np.ndarray) -> np.ndarray:
    norms = np.linalg.norm(vectors, axis=1, keepdims=True)
    unit = vectors / np.maximum(norms, 1e-12)
    return unit @ unit.T


def filter_similarity(kernels: Sequence[np.ndarray], biases: Sequence[np.ndarray]) -> np.ndarray:
    """[B, B] cosine similarity of the pairs' flattened, mean-centred filter banks.

    The mean over pairs is removed first, so the score compares what the global
    parameters change, not the part every pair shares.
    """
    flat = np.concatenate(
        [k.reshape(k.shape[0], -1) for k in kernels] + [b.reshape(b.shape[0], -1) for b in biases],
        axis=1,
    )
    return _cosine_matrix(flat - flat.mean(axis=0, keepdims=True))


def motion_similarity(rotation: np.ndarray, translation: np.ndarray) -> np.ndarray:
    """[B, B] cosine similarity of the relative motions (axis-angle rotation, unit t).

    Args:
      rotation: [B, 3, 3]; translation: [B, 3].
    """
    axis_angles = []
    for matrix in np.asarray(rotation, np.float64):
        vector, _ = _rodrigues_inverse(matrix)
        axis_angles.append(vector)
    unit_t = translation / np.maximum(np.linalg.norm(translation, axis=1, keepdims=True), 1e-12)
    motion = np.concatenate([np.stack(axis_angles), unit_t], axis=1)
    return _cosine_matrix(motion - motion.mean(axis=0, keepdims=True))


def _rodrigues_inverse(matrix: np.ndarray) -> tuple[np.ndarray, float]:
    import cv2

    vector, _ = cv2.Rodrigues(matrix)
    return vector.ravel(), float(np.linalg.norm(vector))


def similarity_correlation(filter_sim: np.ndarray, motion_sim: np.ndarray) -> dict[str, float]:
    """Pearson and Spearman correlation of the off-diagonal entries of two [B, B] matrices."""
    upper = np.triu_indices(filter_sim.shape[0], k=1)
    a, b = filter_sim[upper], motion_sim[upper]
    if a.size < 3:
        return {"pearson": float("nan"), "spearman": float("nan"), "num_pairs": int(a.size)}

    def rank(values):
        return np.argsort(np.argsort(values)).astype(np.float64)

    return {
        "pearson": float(np.corrcoef(a, b)[0, 1]),
        "spearman": float(np.corrcoef(rank(a), rank(b))[0, 1]),
        "num_pairs": int(a.size),
    }


def inspect_pairs(variables: dict, batch: dict[str, np.ndarray], model: nn.Module) -> dict:
    """The filter banks a model generates for a batch of pairs, and how their similarity
    follows the similarity of the pairs' camera motions.

    Returns:
      {"global_params", "kernels", "biases"} of `filter_banks`, "rotation" [B, 3, 3] and
      "translation" [B, 3] (`rotation_translation_of`), "filter_similarity" and
      "motion_similarity" [B, B], and "correlation" (`similarity_correlation`).
    """
    inspected = dict(filter_banks(variables, batch, model=model))
    rotation, translation = rotation_translation_of(batch)
    filter_sim = filter_similarity(inspected["kernels"], inspected["biases"])
    motion_sim = motion_similarity(rotation, translation)
    inspected.update(
        rotation=rotation,
        translation=translation,
        filter_similarity=filter_sim,
        motion_similarity=motion_sim,
        correlation=similarity_correlation(filter_sim, motion_sim),
    )
    return inspected


def draw_filter_banks(
    kernels: Sequence[np.ndarray], example: int, path: str | Path, title: str = ""
) -> Path:
    """Draws one pair's filter banks as image grids (rows: output channels, columns: input
    channels, each cell a k x k filter), one panel per bank, on a shared colour scale."""

    plt = reports.pyplot()

    banks = [np.asarray(k[example]) for k in kernels]  # [k, k, C_in, C_out]
    limit = max(float(np.abs(b).max()) for b in banks) or 1.0
    figure, axes = plt.subplots(1, len(banks), figsize=(5 * len(banks), 5))
    for index, (axis, bank) in enumerate(zip(np.atleast_1d(axes), banks, strict=True)):
        size, _, c_in, c_out = bank.shape
        grid = np.full((c_out * (size + 1), c_in * (size + 1)), np.nan)
        for out_channel in range(c_out):
            for in_channel in range(c_in):
                row, col = out_channel * (size + 1), in_channel * (size + 1)
                grid[row : row + size, col : col + size] = bank[:, :, in_channel, out_channel]
        shown = axis.imshow(grid, cmap="coolwarm", vmin=-limit, vmax=limit)
        axis.set_title(f"bank {index + 1}: {c_in} -> {c_out}")
        axis.set_xlabel("input channel")
        axis.set_ylabel("output channel")
        axis.set_xticks([])
        axis.set_yticks([])
    figure.colorbar(shown, ax=np.atleast_1d(axes).tolist(), fraction=0.02)
    if title:
        figure.suptitle(title)
    return reports.save_figure(figure, path, dpi=80)


def rotation_translation_of(batch: dict[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """The batch's relative pose (validated), for `motion_similarity`."""
    rotation = np.asarray(batch["rotation"], np.float64)
    translation = np.asarray(batch["translation"], np.float64)
    if rotation.shape[1:] != (3, 3) or translation.shape[1:] != (3,):
        raise ValueError(
            f"rotation must be [B, 3, 3] and translation [B, 3], got {rotation.shape} and "
            f"{translation.shape}"
        )
    angles = geometry.rotation_angle_degrees(rotation)
    if not np.all(np.isfinite(angles)):
        raise ValueError("rotation contains non-finite values")
    return rotation, translation


__all__ = [
    "draw_filter_banks",
    "filter_banks",
    "filter_similarity",
    "motion_similarity",
    "rotation_translation_of",
    "similarity_correlation",
]
