"""What a trained depth model has learned, measured per test pair.

Two instruments:

- `depth_statistics` separates the two things a two-view depth model must get right:
  each pair's depth scale (does the pair's mean predicted inverse depth follow the
  truth across pairs?) and the structure within a pair (does the predicted map
  correlate with the true one pixel by pixel?). A model that predicts a constant has
  no within-pair correlation; one whose global module ignores the camera motion gets
  the structure but not the scale.
- `pose_probe` answers "do the global parameters encode the relative camera pose?"
  (the paper's Sec. 4.4): a small MLP regresses the rotation (axis-angle) and the
  translation direction from the global parameters of the training pairs, and is
  scored on the test pairs in degrees, next to predicting the training mean pose.
  `global_params_pose_errors` reads g directly as the pose the epipolar term trains it
  to stand for (`gld.models.global_local.global_params_pose`), with no probe in between.
  The probe on the global encoder itself, frozen or trained, is
  `gld.analysis.encoder_pose`'s.

`collect` runs a model over a split once and keeps what both need.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from typing import Any

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
import optax

from gld import geometry
from gld.evaluation import evaluate as evaluation
from gld.losses import supervised as losses
from gld.models import global_local as model_lib
from gld.models import layers


def rotation_vector(rotation: np.ndarray) -> np.ndarray:
    """Axis-angle vector [..., 3] (radians) of rotation matrices [..., 3, 3] (angle < pi)."""
    rotation = np.asarray(rotation, np.float64)
    skew = np.stack(
        [
            rotation[..., 2, 1] - rotation[..., 1, 2],
            rotation[..., 0, 2] - rotation[..., 2, 0],
            rotation[..., 1, 0] - rotation[..., 0, 1],
        ],
        axis=-1,
    )
    trace = rotation[..., 0, 0] + rotation[..., 1, 1] + rotation[..., 2, 2]
    angle = np.arccos(np.clip((trace - 1.0) / 2.0, -1.0, 1.0))
    sine = np.sin(angle)
    # angle / (2 sin angle) -> 1/2 as the angle -> 0.
    factor = np.where(sine > 1e-8, angle / np.maximum(2.0 * sine, 1e-12), 0.5)
    return skew * factor[..., None]


def _pair_statistics(
    inv_depth_pred: np.ndarray, inv_depth_true: np.ndarray, valid: np.ndarray
) -> dict[str, float]:
    """Mean, standard deviation and correlation over the valid pixels of one pair."""
    pred, true = inv_depth_pred[valid], inv_depth_true[valid]
    if pred.size < 2:
        return {"pred_mean": math.nan, "true_mean": math.nan, "pred_std": math.nan,
                "true_std": math.nan, "correlation": math.nan}  # fmt: skip
    pred_std, true_std = float(pred.std()), float(true.std())
    correlation = (
        float(np.mean((pred - pred.mean()) * (true - true.mean())) / (pred_std * true_std))
        if pred_std > 0 and true_std > 0
        else 0.0
    )
    return {
        "pred_mean": float(pred.mean()),
        "true_mean": float(true.mean()),
        "pred_std": pred_std,
        "true_std": true_std,
        "correlation": correlation,
    }


def pair_statistics(
    inv_depth_pred: np.ndarray, inv_depth_true: np.ndarray, valid: np.ndarray
) -> dict[str, np.ndarray]:
    """Per-pair inverse-depth statistics of a batch, over each pair's valid pixels.

    Args:
      inv_depth_pred, inv_depth_true: [N, H, W].
      valid: [N, H, W] bool.

    Returns:
      {"pred_mean", "true_mean", "pred_std", "true_std", "correlation"}, each [N]
      (NaN for a pair with fewer than two valid pixels).
    """
    rows = [
        _pair_statistics(np.asarray(pred, np.float64), np.asarray(true, np.float64), mask)
        for pred, true, mask in zip(
            inv_depth_pred, inv_depth_true, np.asarray(valid, bool), strict=True
        )
    ]
    return {name: np.array([row[name] for row in rows]) for name in _PAIR_STATISTICS}


_PAIR_STATISTICS = ("pred_mean", "true_mean", "pred_std", "true_std", "correlation")


def collect(
    apply_fn: Callable[[dict], dict],
    source: Sequence[Any],
    *,
    batch_size: int = 16,
    flow_source: str = "estimated",
    max_examples: int = 0,
) -> dict[str, np.ndarray]:
    """Runs a model over a split (unaugmented, ||t|| = 1) and keeps per-pair values.

    Args:
      apply_fn: batch (the example contract) -> the model's outputs (`inv_depth`
        [B, H, W], and `global_params` [B, G] for the global-local model).
      source: random-access records of the split.
      batch_size: evaluation batch size.
      flow_source: the flow the model is given ("estimated" or "gt").
      max_examples: only the first N pairs (0 = all).

    Returns:
      {"pred_mean", "true_mean", "pred_std", "true_std", "correlation"}: [N] inverse-depth
      statistics over each pair's valid pixels; "global_params" [N, G] (if the model has
      them); "rotation_vector" [N, 3] radians and "translation" [N, 3] unit norm, the
      true relative pose.
    """
    collected: dict[str, list] = {}
    batches = evaluation.split_batches(
        source,
        batch_size=batch_size,
        flow_source=flow_source,
        max_examples=max_examples,
        all_processes=False,
    )
    for batch in batches:
        outputs = apply_fn(batch)
        inv_pred = np.asarray(outputs["inv_depth"], np.float64)
        valid = np.asarray(batch["depth_valid"], bool) & (np.asarray(batch["depth"]) > 0)
        inv_true = np.asarray(losses.inverse_depth_target(batch["depth"], valid), np.float64)
        rows = np.flatnonzero(np.asarray(batch["example_mask"], bool))
        for name, values in pair_statistics(inv_pred[rows], inv_true[rows], valid[rows]).items():
            collected.setdefault(name, []).extend(values)
        for row in rows:
            if "global_params" in outputs:
                collected.setdefault("global_params", []).append(
                    np.asarray(outputs["global_params"][row], np.float64)
                )
            collected.setdefault("rotation_vector", []).append(
                rotation_vector(batch["rotation"][row])
            )
            collected.setdefault("translation", []).append(
                np.asarray(batch["translation"][row], np.float64)
            )
    return {name: np.asarray(values) for name, values in collected.items()}


def _correlation(a: np.ndarray, b: np.ndarray) -> float:
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    if np.ptp(a) == 0 or np.ptp(b) == 0:  # a constant has no correlation
        return 0.0
    return float(np.corrcoef(a, b)[0, 1])


def depth_statistics(collected: dict[str, np.ndarray]) -> dict[str, float]:
    """Scale and structure of the predictions against the truth, over pairs.

    Returns:
      pair_scale_correlation: correlation across pairs of the mean predicted and the
        mean true inverse depth (1: every pair's scale is right up to one factor).
      pair_scale_ratio: std across pairs of the predicted means / of the true means.
      within_pair_correlation: median over pairs of the pixel-wise correlation.
      within_pair_std_ratio: median over pairs of predicted / true standard deviation
        (0 for a constant map).
      global_params_std: mean over the G dimensions of the std across pairs (absent
        without global parameters).
    """
    finite = np.isfinite(collected["pred_mean"]) & np.isfinite(collected["true_mean"])
    pred_mean, true_mean = collected["pred_mean"][finite], collected["true_mean"][finite]
    std_ratio = collected["pred_std"][finite] / np.maximum(collected["true_std"][finite], 1e-12)
    statistics = {
        "pair_scale_correlation": _correlation(pred_mean, true_mean),
        "pair_scale_ratio": float(pred_mean.std() / max(true_mean.std(), 1e-12)),
        "within_pair_correlation": float(np.median(collected["correlation"][finite])),
        "within_pair_std_ratio": float(np.median(std_ratio)),
    }
    if "global_params" in collected:
        statistics["global_params_std"] = float(collected["global_params"].std(axis=0).mean())
    return statistics


class PoseMLP(nn.Module):
    """The probe: an MLP (LeakyReLU) from global parameters to [rotation vector, t]."""

    hidden: Sequence[int] = (256, 256)

    @nn.compact
    def __call__(self, features: jax.Array) -> jax.Array:
        """features: [N, G] -> [N, 6] (axis-angle in radians, translation direction)."""
        for width in self.hidden:
            features = jax.nn.leaky_relu(nn.Dense(width)(features), 0.2)
        return nn.Dense(6)(features)


def _pose_targets(collected: dict[str, np.ndarray]) -> np.ndarray:
    return np.concatenate([collected["rotation_vector"], collected["translation"]], axis=-1)


def pose_errors(predicted: np.ndarray, target: np.ndarray) -> dict[str, float]:
    """Mean rotation and translation-direction errors (degrees) of [N, 6] poses."""
    rotation = geometry.rotation_matrix(predicted[:, :3])
    rotation_true = geometry.rotation_matrix(target[:, :3])
    return {
        "rotation_deg": float(np.mean(geometry.rotation_error_degrees(rotation, rotation_true))),
        "translation_deg": float(
            np.mean(geometry.translation_error_degrees(predicted[:, 3:], target[:, 3:]))
        ),
    }


def pose_probe(
    train: dict[str, np.ndarray],
    test: dict[str, np.ndarray],
    *,
    hidden: Sequence[int] = (256, 256),
    steps: int = 2000,
    learning_rate: float = 1e-3,
    seed: int = 0,
) -> dict[str, dict[str, float]]:
    """Regresses the relative pose from the global parameters (the paper's Sec. 4.4 MLP,
    trained on frozen features: the "MLP only" setting).

    Features and targets are standardised with the training pairs' statistics; the MLP
    is trained full-batch with Adam on the L1 error of [rotation vector, translation
    direction].

    Args:
      train, test: `collect` outputs (need "global_params", "rotation_vector",
        "translation").

    Returns:
      {"probe": {...}, "mean_pose": {...}}: mean rotation and translation-direction
      errors (degrees) on the test pairs of the probe and of predicting the training
      pairs' mean pose.
    """
    for name, collected in (("train", train), ("test", test)):
        if "global_params" not in collected:
            raise ValueError(f"{name} pairs have no global parameters to probe")
    train_features, test_features = train["global_params"], test["global_params"]
    center = train_features.mean(0)
    scale = np.maximum(train_features.std(0), 1e-8)
    inputs = jnp.asarray((train_features - center) / scale, jnp.float32)
    test_inputs = jnp.asarray((test_features - center) / scale, jnp.float32)
    # Rotation vectors (~0.1 rad) and unit translations differ in scale: standardise
    # the targets too, so that the L1 loss weighs both.
    raw_targets = _pose_targets(train)
    target_center = raw_targets.mean(0)
    target_scale = np.maximum(raw_targets.std(0), 1e-8)
    targets = jnp.asarray((raw_targets - target_center) / target_scale, jnp.float32)

    model = PoseMLP(hidden=tuple(hidden))
    params = layers.init_once(model, jax.random.key(seed), inputs[:1])
    optimizer = optax.adam(learning_rate)

    @jax.jit
    def step(params, opt_state):
        def loss_fn(params):
            return jnp.mean(jnp.abs(model.apply(params, inputs) - targets))

        grads = jax.grad(loss_fn)(params)
        updates, opt_state = optimizer.update(grads, opt_state, params)
        return optax.apply_updates(params, updates), opt_state

    opt_state = optimizer.init(params)
    for _ in range(steps):
        params, opt_state = step(params, opt_state)
    test_targets = _pose_targets(test)
    predicted = np.asarray(model.apply(params, test_inputs), np.float64)
    predicted = predicted * target_scale + target_center
    mean_pose = np.broadcast_to(target_center, test_targets.shape)
    return {
        "probe": pose_errors(predicted, test_targets),
        "mean_pose": pose_errors(mean_pose, test_targets),
    }


def global_params_pose_errors(collected: dict[str, np.ndarray]) -> dict[str, float]:
    """Mean errors (degrees) of the pose six global parameters stand for, read with
    `gld.models.global_local.global_params_pose`: what a model trained with the epipolar term has
    made of g. The translation direction is scored up to its sign, which the epipolar
    constraint does not fix.

    Args:
      collected: a `collect` output with "global_params" [N, 6].
    """
    if "global_params" not in collected or collected["global_params"].shape[1:] != (6,):
        raise ValueError("reading g as a pose needs six global parameters per pair")
    pose = model_lib.global_params_pose(np.asarray(collected["global_params"], np.float64))
    rotation_true = geometry.rotation_matrix(collected["rotation_vector"])
    angle = geometry.translation_error_degrees(pose["translation"], collected["translation"])
    return {
        "rotation_deg": float(
            np.mean(geometry.rotation_error_degrees(pose["rotation"], rotation_true))
        ),
        "translation_deg": float(np.mean(np.minimum(angle, 180.0 - angle))),
    }
