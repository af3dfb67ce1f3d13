"""Classical (untrained) depth baselines and references: dataset mean, per-pair oracle
constant, triangulation with the true pose, SfM.

Every method follows one protocol, so the evaluation launcher treats them alike:

    method = CLASSICAL[name](**options)
    if method.needs_training_data:
        method.fit(training_examples)
    outputs = method.predict(batch)  # {'inv_depth', 'depth', ...} numpy, [B, H, W]

`batch` follows the example contract (numpy or JAX arrays with a leading batch axis:
'flow' [B, H, W, 2] pixels I1 -> I2, normalised 'intrinsics1'/'intrinsics2' [B, 4],
'rotation' [B, 3, 3], 'translation' [B, 3] with X2 = R X1 + t). All predictions are
in the scale of the contract: the pair's translation has norm 1. Predictions are
never NaN: pixels (or whole pairs) a method cannot handle get a defined fallback and
are counted in the outputs, so they stay in every mean.

`OraclePairMedian` reads the ground truth of the pair it predicts: it is a reference,
not a method, and every table shows it with its label (`LABELS`), as it shows `SfMFlow`,
the classical pipeline on the evaluated flow.
"""

from __future__ import annotations

import warnings
from collections.abc import Iterable, Mapping
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from gld import flow_pose, geometry
from gld.models import layers

Batch = Mapping[str, Any]
Array = Any  # np.ndarray | jax.Array

# Triangulated points closer than this (in units of the baseline, ||t|| = 1) are
# treated as failures: they come from near-degenerate rays, not from real geometry.
DEFAULT_MIN_DEPTH = 1e-2


def _require(batch: Batch, keys: Iterable[str]) -> None:
    missing = [key for key in keys if key not in batch]
    if missing:
        raise ValueError(f"batch lacks {missing}; it has {sorted(batch)}")


def _flow_of(batch: Batch) -> np.ndarray:
    _require(batch, ["flow"])
    flow = batch["flow"]
    if flow.ndim != 4 or flow.shape[-1] != 2:
        raise ValueError(f"'flow' must be [B, H, W, 2], got shape {tuple(flow.shape)}")
    return flow


def triangulate_batch(
    flow: Array,
    intrinsics1: Array,
    intrinsics2: Array,
    rotation: Array,
    translation: Array,
    *,
    min_depth: float = DEFAULT_MIN_DEPTH,
    fallback_inv_depth: float = layers.INITIAL_INV_DEPTH,
) -> dict[str, Array]:
    """Per-pixel linear triangulation of a batch with a given pose (pure, jittable).

    JAX arrays (or tracers) in give JAX arrays out; numpy arrays in give numpy arrays
    out, without touching JAX (so that dataset builders can call it in worker processes).

    The translation is rescaled to unit norm (the evaluation scale). A pixel is
    triangulated when its depth is finite, at least `min_depth`, and its point lies in
    front of camera 2; every other pixel gets the median triangulated inverse depth of
    its pair (or `fallback_inv_depth` when none of the pair's pixels triangulates).

    Args:
      flow: [B, H, W, 2] pixels, I1 -> I2.
      intrinsics1, intrinsics2: [B, 4] normalised.
      rotation, translation: [B, 3, 3], [B, 3]; X2 = R X1 + t.
      min_depth: nearest accepted depth, in units of ||t||.
      fallback_inv_depth: inverse depth of pairs with no triangulated pixel.

    Returns:
      'inv_depth', 'depth': [B, H, W] positive and finite; 'triangulated': [B, H, W] bool;
      'untriangulated': [B] int32 count of filled pixels.
    """
    inputs = (flow, intrinsics1, intrinsics2, rotation, translation)
    xp = jnp if any(isinstance(value, jax.Array) for value in inputs) else np
    height, width = flow.shape[-3:-1]
    flow = xp.asarray(flow, xp.float32)
    rotation = xp.asarray(rotation, xp.float32)
    translation = xp.asarray(translation, xp.float32)
    camera_matrix1 = geometry.intrinsics_matrix(xp.asarray(intrinsics1, xp.float32), height, width)
    camera_matrix2 = geometry.intrinsics_matrix(xp.asarray(intrinsics2, xp.float32), height, width)
    norm = xp.linalg.norm(translation, axis=-1, keepdims=True)
    unit_translation = translation / xp.maximum(norm, 1e-12)

    depth = geometry.triangulate_depth(
        flow, camera_matrix1, camera_matrix2, rotation, unit_translation
    )
    safe_depth = xp.where(xp.isfinite(depth), depth, 0.0)
    points2 = geometry.transform_points(
        geometry.backproject(safe_depth, camera_matrix1), rotation, unit_translation
    )
    triangulated = (
        xp.isfinite(depth)
        & (depth >= min_depth)
        & (points2[..., 2] > 0)
        & xp.all(xp.isfinite(flow), axis=-1)
        & (norm[..., None] > 1e-12)
    )
    inv_depth = xp.where(triangulated, 1.0 / xp.where(triangulated, depth, 1.0), xp.nan)
    with warnings.catch_warnings():
        # numpy warns about a pair with no triangulated pixel; its fallback is next.
        warnings.simplefilter("ignore", RuntimeWarning)
        pair_median = xp.nanmedian(inv_depth, axis=(-2, -1), keepdims=True)
    pair_median = xp.where(xp.isfinite(pair_median), pair_median, fallback_inv_depth)
    inv_depth = xp.where(triangulated, inv_depth, pair_median)
    return {
        "inv_depth": inv_depth,
        "depth": 1.0 / inv_depth,
        "triangulated": triangulated,
        "untriangulated": xp.sum(~triangulated, axis=(-2, -1)).astype(xp.int32),
    }


def _to_numpy(outputs: Mapping[str, Any]) -> dict[str, np.ndarray]:
    return {key: np.asarray(value) for key, value in outputs.items()}


class DatasetMean:
    """The paper's "Dataset-Mean": the mean training inverse depth, everywhere.

    The mean is over all valid pixels of all training examples, each example's depth
    scale-normalised so that its translation has norm 1.
    """

    needs_training_data = True

    def __init__(self, inv_depth: float | None = None):
        """Args: inv_depth: the mean, if already known (else call `fit`)."""
        self.inv_depth = inv_depth

    def fit(self, examples: Iterable[Batch]) -> DatasetMean:
        """Computes the mean from examples or batches with 'depth' [(B,) H, W] (and,
        where present, 'depth_valid' and 'translation' [(B,) 3])."""
        inv_depth_sum, pixel_count = 0.0, 0
        for example in examples:
            _require(example, ["depth"])
            depth = np.asarray(example["depth"], np.float64)
            valid = geometry.valid_depth(depth)
            if "depth_valid" in example:
                valid &= np.asarray(example["depth_valid"], bool)
            inv_depth = np.where(valid, 1.0 / np.where(valid, depth, 1.0), 0.0)
            if "translation" in example:
                # Depth / ||t|| is the normalised depth, so inverse depth scales by ||t||.
                norm = np.linalg.norm(np.asarray(example["translation"], np.float64), axis=-1)
                inv_depth = inv_depth * np.reshape(norm, norm.shape + (1, 1))
            inv_depth_sum += float(inv_depth.sum())
            pixel_count += int(valid.sum())
        if pixel_count == 0:
            raise ValueError("no valid depth pixel in the training examples")
        self.inv_depth = inv_depth_sum / pixel_count
        return self

    def predict(self, batch: Batch) -> dict[str, np.ndarray]:
        """Constant map {'inv_depth', 'depth'}: [B, H, W], sized like 'flow'."""
        batch_size, height, width, _ = _flow_of(batch).shape
        if self.inv_depth is None:
            raise ValueError("DatasetMean has no mean yet: call fit(training_examples) first")
        inv_depth = np.full((batch_size, height, width), self.inv_depth, np.float32)
        return {"inv_depth": inv_depth, "depth": 1.0 / inv_depth}


class OraclePairMedian:
    """Per-pair oracle constant: each pair's own median true inverse depth, everywhere.

    It reads the pair's ground truth ('depth', 'depth_valid'), so it is an oracle, not a
    method. Among constant predictions it is the best one of each pair under Abs-Inv (the
    median minimises the mean absolute error), so a model that beats it has learned
    structure within the pair, not only the pair's scale.
    """

    label = "per-pair oracle constant (sees the truth)"
    needs_training_data = False

    def __init__(self, *, fallback_inv_depth: float = layers.INITIAL_INV_DEPTH):
        """Args: fallback_inv_depth: prediction of pairs without a valid pixel (which no
        metric counts)."""
        self.fallback_inv_depth = fallback_inv_depth

    def fit(self, examples: Iterable[Batch]) -> OraclePairMedian:
        del examples
        return self

    def predict(self, batch: Batch) -> dict[str, np.ndarray]:
        """Constant map per pair {'inv_depth', 'depth'}: [B, H, W], sized like 'depth'.

        Args:
          batch: 'depth' [B, H, W] in the contract's scale (||t|| = 1) and, where present,
            'depth_valid' [B, H, W] bool; pixels with non-positive or non-finite depth
            are invalid too.
        """
        _require(batch, ["depth"])
        depth = np.asarray(batch["depth"], np.float64)
        if depth.ndim != 3:
            raise ValueError(f"'depth' must be [B, H, W], got shape {depth.shape}")
        valid = geometry.valid_depth(depth)
        if "depth_valid" in batch:
            valid &= np.asarray(batch["depth_valid"], bool)
        inv_depth = np.empty(depth.shape, np.float32)
        for pair, (pair_depth, pair_valid) in enumerate(zip(depth, valid, strict=True)):
            if pair_valid.any():
                inv_depth[pair] = np.median(1.0 / pair_depth[pair_valid])
            else:
                inv_depth[pair] = self.fallback_inv_depth
        return {"inv_depth": inv_depth, "depth": 1.0 / inv_depth}


class TriangulationGtPose:
    """Per-pixel linear triangulation from the flow and the true pose and intrinsics."""

    needs_training_data = False

    def __init__(
        self,
        *,
        min_depth: float = DEFAULT_MIN_DEPTH,
        fallback_inv_depth: float = layers.INITIAL_INV_DEPTH,
    ):
        self.min_depth = min_depth
        self.fallback_inv_depth = fallback_inv_depth
        self._triangulate = jax.jit(
            triangulate_batch,
            static_argnames=("min_depth", "fallback_inv_depth"),
        )

    def fit(self, examples: Iterable[Batch]) -> TriangulationGtPose:
        del examples
        return self

    def predict(self, batch: Batch) -> dict[str, np.ndarray]:
        """{'inv_depth', 'depth', 'triangulated' [B, H, W], 'untriangulated' [B]}."""
        flow = _flow_of(batch)
        _require(batch, ["intrinsics1", "intrinsics2", "rotation", "translation"])
        outputs = self._triangulate(
            flow,
            batch["intrinsics1"],
            batch["intrinsics2"],
            batch["rotation"],
            batch["translation"],
            min_depth=self.min_depth,
            fallback_inv_depth=self.fallback_inv_depth,
        )
        return _to_numpy(outputs)


class SfMFlow:
    """Two-view structure from motion on the flow: essential matrix, pose, triangulation.

    The pose is the essential matrix's from the flow (`gld.flow_pose`: RANSAC on a
    grid of correspondences, cheirality); t has unit norm, which is exactly the
    evaluation scale (the true ||t|| = 1), so the depth is directly comparable with the
    ground truth. A pair whose pose fails (`gld.flow_pose` says when) is flagged in
    'failed' and predicted as the constant `fallback_inv_depth` (by default the training
    set's mean inverse depth, the Dataset-Mean prediction, computed by `fit`), so it
    stays in every mean.

    It learns nothing and reads no ground truth of the pair it predicts (only the
    fallback comes from the training split), so every evaluation shows it on the same
    flow as a reference: what the flow alone gives (`LABELS`).
    """

    label = "classical pipeline on the same flow (no training)"

    def __init__(
        self,
        *,
        ransac_threshold_pixels: float = 0.5,
        confidence: float = 0.999,
        max_correspondences: int = 5000,
        min_inliers: int = 20,
        min_parallax_pixels: float = 0.5,
        min_depth: float = DEFAULT_MIN_DEPTH,
        fallback_inv_depth: float | None = None,
    ):
        """Args: see the class docstring; `fallback_inv_depth=None` means the training
        mean (then `needs_training_data` is True and `fit` must be called first)."""
        self.needs_training_data = fallback_inv_depth is None
        self.ransac_threshold_pixels = ransac_threshold_pixels
        self.confidence = confidence
        self.max_correspondences = max_correspondences
        self.min_inliers = min_inliers
        self.min_parallax_pixels = min_parallax_pixels
        self.settings = flow_pose.PoseSettings(
            ransac_threshold_pixels=ransac_threshold_pixels,
            confidence=confidence,
            max_correspondences=max_correspondences,
            min_inliers=min_inliers,
            min_parallax_pixels=min_parallax_pixels,
        )
        self.min_depth = min_depth
        self.fallback_inv_depth = fallback_inv_depth
        self._triangulate = jax.jit(
            triangulate_batch,
            static_argnames=("min_depth", "fallback_inv_depth"),
        )

    def fit(self, examples: Iterable[Batch]) -> SfMFlow:
        """Sets the fallback of failed pairs to the examples' mean inverse depth."""
        self.fallback_inv_depth = DatasetMean().fit(examples).inv_depth
        return self

    def estimate_pose(
        self, flow: np.ndarray, camera_matrix1: np.ndarray, camera_matrix2: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, bool]:
        """Relative pose of one pair from its flow (`gld.flow_pose.estimate_pose` with
        this pipeline's settings): rotation [3, 3], unit translation [3] (X2 = R X1 + t),
        and whether it succeeded (identity and zero translation when not)."""
        return flow_pose.estimate_pose(flow, camera_matrix1, camera_matrix2, self.settings)

    def predict(self, batch: Batch) -> dict[str, np.ndarray]:
        """{'inv_depth', 'depth', 'triangulated' [B, H, W], 'untriangulated' [B],
        'failed' [B] bool, 'rotation' [B, 3, 3], 'translation' [B, 3]} (estimated pose)."""
        flow = np.asarray(_flow_of(batch), np.float64)
        _require(batch, ["intrinsics1", "intrinsics2"])
        if self.fallback_inv_depth is None:
            raise ValueError(
                "SfMFlow has no fallback for failed pairs: call fit(training_examples) or "
                "pass fallback_inv_depth"
            )
        batch_size, height, width, _ = flow.shape
        intrinsics1 = np.asarray(batch["intrinsics1"], np.float64)
        intrinsics2 = np.asarray(batch["intrinsics2"], np.float64)
        camera_matrices1 = geometry.intrinsics_matrix(intrinsics1, height, width)
        camera_matrices2 = geometry.intrinsics_matrix(intrinsics2, height, width)
        poses = flow_pose.in_parallel(
            self.estimate_pose, list(zip(flow, camera_matrices1, camera_matrices2, strict=True))
        )
        rotations = np.reshape([rotation for rotation, _, _ in poses], (batch_size, 3, 3))
        translations = np.reshape([translation for _, translation, _ in poses], (batch_size, 3))
        failed = np.array([not succeeded for _, _, succeeded in poses], bool)
        outputs = _to_numpy(
            self._triangulate(
                flow.astype(np.float32),
                intrinsics1.astype(np.float32),
                intrinsics2.astype(np.float32),
                rotations.astype(np.float32),
                translations.astype(np.float32),
                min_depth=self.min_depth,
                fallback_inv_depth=self.fallback_inv_depth,
            )
        )
        pair_failed = failed[:, None, None]
        outputs["inv_depth"] = np.where(
            pair_failed, np.float32(self.fallback_inv_depth), outputs["inv_depth"]
        ).astype(np.float32)
        outputs["depth"] = 1.0 / outputs["inv_depth"]
        outputs["triangulated"] = outputs["triangulated"] & ~pair_failed
        outputs["untriangulated"] = np.where(failed, height * width, outputs["untriangulated"])
        outputs.update(
            failed=failed,
            rotation=rotations.astype(np.float32),
            translation=translations.astype(np.float32),
        )
        return outputs


CLASSICAL: dict[str, type] = {
    "dataset_mean": DatasetMean,
    "oracle_pair_median": OraclePairMedian,
    "triangulation_gt_pose": TriangulationGtPose,
    "sfm_flow": SfMFlow,
}

# What every table writes next to a reference's name: the oracle sees the ground truth and
# must never be read as a method; the classical pipeline says what the flow alone gives.
LABELS: dict[str, str] = {
    "oracle_pair_median": OraclePairMedian.label,
    "sfm_flow": SfMFlow.label,
}
