"""Where a self-supervised depth run's error comes from: its scale, its shape or its pose,
and whether the photometric loss is lowest at the truth on a dataset.

Three questions, each answered on a split's pairs (`experiments.diagnose_self_supervised`):

* Scale or shape. The run's depth is scored as the protocol scores it (units of its
  predicted translation, ||t|| = 1) and again with each pair's scale taken from the truth
  (`median_scaled`: the median inverse depth over valid pixels made the truth's). The
  second score has no scale error left; against the per-pair oracle constant (the flat map
  at the same median) it says whether the map's shape helps.
* Pose. The predicted rotation and translation direction against the true ones, in
  degrees, beside the error of predicting no rotation.
* The loss itself. `photometric_at_truth`: the photometric loss with the true depth and
  pose, and with one of them spoiled (a flat depth; half, twice or reversed translation).
  If the truth is not the lowest, no optimiser will find it; if it is, a run that sits
  above it has not found the basin.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping

import jax
import jax.numpy as jnp
import numpy as np

from gld import geometry
from gld.evaluation import evaluate as evaluation
from gld.evaluation import metrics
from gld.losses import photometric
from gld.models import layers
from gld.models.baselines import classical

# The photometric loss at the true depth and pose, and with one of them spoiled: the
# translation is multiplied by the factor, or the depth replaced by its median.
TRUTH = "truth"
SPOILED_TRUTH: Mapping[str, dict] = {
    TRUTH: {},
    "flat depth, true pose": {"flat": True},
    "true depth, half translation": {"translation_factor": 0.5},
    "true depth, twice the translation": {"translation_factor": 2.0},
    "true depth, reversed translation": {"translation_factor": -1.0},
}


def _valid_truth(batch: Mapping[str, np.ndarray]) -> np.ndarray:
    """The pixels scored: valid in the batch and of finite positive true depth."""
    depth = np.asarray(batch["depth"], np.float64)
    return geometry.valid_depth(depth) & np.asarray(batch["depth_valid"], bool)


def _truth_median_inv_depth(batch: Mapping[str, np.ndarray]) -> np.ndarray:
    """Each pair's median true inverse depth, as a map [B, H, W] (the per-pair oracle
    constant's prediction)."""
    return classical.OraclePairMedian().predict(batch)["inv_depth"].astype(np.float64)


def median_scaled(depth: np.ndarray, batch: Mapping[str, np.ndarray]) -> np.ndarray:
    """Predicted depth [B, H, W] rescaled per pair so that its median inverse depth over
    the valid truth pixels is the truth's: the prediction's shape at the truth's scale."""
    inv_depth = 1.0 / np.asarray(depth, np.float64)
    valid = _valid_truth(batch)
    truth = _truth_median_inv_depth(batch)
    scaled = inv_depth.copy()
    for pair, (pair_inv_depth, pair_valid) in enumerate(zip(inv_depth, valid, strict=True)):
        if pair_valid.any():  # a pair without a valid pixel counts in no metric
            scaled[pair] *= truth[pair, 0, 0] / np.median(pair_inv_depth[pair_valid])
    return (1.0 / scaled).astype(np.float32)


def pose_errors(outputs: Mapping[str, np.ndarray], batch: Mapping[str, np.ndarray]) -> dict:
    """Per-pair pose errors in degrees, each [B]: 'rotation_deg' and 'translation_deg' of
    the prediction (`metrics.pose_errors`), 'identity_rotation_deg' of predicting no
    rotation."""
    rotation_true = np.asarray(batch["rotation"], np.float64)
    errors = metrics.pose_errors(
        np.asarray(outputs["rotation"], np.float64),
        np.asarray(outputs["translation"], np.float64),
        rotation_true,
        np.asarray(batch["translation"], np.float64),
    )
    return {**errors, "identity_rotation_deg": geometry.rotation_angle_degrees(rotation_true)}


def diagnose_model(model, variables: dict, batches: Iterable[dict]) -> dict[str, np.ndarray]:
    """Per-pair diagnosis of a self-supervised model (outputs 'depth', 'rotation',
    'translation') over `batches` (the example contract, with 'example_mask').

    Returns [N] arrays over the pairs the evaluation counts (real, with valid truth):
    'abs_inv' and 's_rmse' as scored, 'abs_inv_median_scaled' and 's_rmse_median_scaled',
    and `pose_errors`' keys.
    """
    apply = jax.jit(lambda v, b: layers.apply_model(model, v, b, train=False))
    rows: dict[str, list[np.ndarray]] = {}
    for batch in batches:
        inputs = {key: batch[key] for key in layers.input_keys(model)}
        outputs = {
            key: np.asarray(value)
            for key, value in apply(variables, inputs).items()
            if key in ("depth", "rotation", "translation")
        }
        missing = {"depth", "rotation", "translation"} - set(outputs)
        if missing:
            raise ValueError(f"the model does not predict {sorted(missing)}: not self-supervised")
        truth = {key: jnp.asarray(batch[key]) for key in ("depth", "depth_valid", "example_mask")}
        for suffix, depth in (
            ("", outputs["depth"]),
            ("_median_scaled", median_scaled(outputs["depth"], batch)),
        ):
            # The evaluation's own scoring and its rule for the pairs that count.
            scored = evaluation.score_batch(jnp.asarray(depth), truth)
            mask = np.asarray(scored["example_mask"], bool)
            for name in ("abs_inv", "s_rmse"):
                rows.setdefault(name + suffix, []).append(np.asarray(scored[name])[mask])
        for name, value in pose_errors(outputs, batch).items():
            rows.setdefault(name, []).append(np.asarray(value)[mask])
    return {name: np.concatenate(values) for name, values in rows.items()}


def photometric_at_truth(batches: Iterable[dict]) -> dict[str, dict[str, float]]:
    """The self-supervised loss's photometric term and auto-mask fraction at the true
    depth and pose and at each spoiled truth of `SPOILED_TRUTH`, averaged over the real
    pairs of `batches` (rows whose 'example_mask' is False are left out).

    Pixels without a valid true depth take the pair's median true inverse depth.
    """
    sums: dict[str, np.ndarray] = {name: np.zeros(2) for name in SPOILED_TRUTH}
    count = 0
    loss = jax.jit(photometric.self_supervised_loss)
    for batch in batches:
        real = np.asarray(batch.get("example_mask", np.ones(len(batch["depth"]), bool)), bool)
        if not real.any():
            continue
        batch = {key: np.asarray(value)[real] for key, value in batch.items() if key != "id"}
        valid = _valid_truth(batch)
        median = _truth_median_inv_depth(batch)
        filled = np.where(valid, 1.0 / np.where(valid, batch["depth"], 1.0), median)
        images = {key: jnp.asarray(batch[key]) for key in photometric.BATCH_KEYS if key in batch}
        for name, spoil in SPOILED_TRUTH.items():
            inv_depth = median if spoil.get("flat") else filled
            translation = np.asarray(batch["translation"]) * spoil.get("translation_factor", 1.0)
            outputs = {
                "inv_depth_scales": (jnp.asarray(inv_depth, jnp.float32),),
                "rotation": jnp.asarray(batch["rotation"], jnp.float32),
                "translation": jnp.asarray(translation, jnp.float32),
            }
            _, terms = loss(outputs, images)
            terms = [float(terms["photometric"]), float(terms["auto_mask_fraction"])]
            sums[name] += np.asarray(terms) * real.sum()
        count += int(real.sum())
    if not count:
        raise ValueError("photometric_at_truth needs at least one real pair")
    return {
        name: {"photometric": total[0] / count, "auto_mask_fraction": total[1] / count}
        for name, total in sums.items()
    }
