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
  `fit_pose_probe` trains the MLP on the global encoder itself, frozen or not, from a
  trained model's encoder (`pretrained_global_encoder`) or a random one;
  `pose_probe_settings` runs the paper's four settings of its pose table and keeps each
  one's predicted poses.

`collect` runs a model over a split once and keeps what both need.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable, Sequence
from typing import Any

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
import optax

from gld import geometry, input_pipeline
from gld.evaluation import evaluate as evaluation
from gld.losses import supervised as losses
from gld.models import global_local as model_lib
from gld.models import layers
from gld.models.global_encoder import GlobalEncoder
from gld.runs import state


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


def _pose_errors(predicted: np.ndarray, target: np.ndarray) -> dict[str, float]:
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
    params = model.init(jax.random.key(seed), inputs[:1])
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
        "probe": _pose_errors(predicted, test_targets),
        "mean_pose": _pose_errors(mean_pose, test_targets),
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


# Options of the probe's global encoder that must match a trained model's for its
# parameters to fit and see the inputs it was trained on (`pretrained_global_encoder`).
ENCODER_OPTIONS = (
    "encoder_channels",
    "encoder_strides",
    "global_dim",
    "kernel_size",
    "encoder_norm",
    "use_image_pair",
    "encoder_coordinates",
    "flow_scale",
)

# The paper's pose table (Sec. 4.4): setting -> (start from the trained encoder, train it).
POSE_PROBE_SETTINGS = {
    "scratch_mlp": (False, False),
    "pretrained_mlp": (True, False),
    "scratch_full": (False, True),
    "pretrained_full": (True, True),
}


def pretrained_global_encoder(model: nn.Module, variables: dict) -> dict[str, Any]:
    """The global encoder of a trained global-local model, as `fit_pose_probe` options.

    Args:
      model: a `gld.models.global_local.GlobalLocal` whose g comes from its global encoder.
      variables: its variables (e.g. from `gld.runs.workdir.load_trained`).

    Returns:
      {"encoder_channels": tuple[int, ...], "encoder_strides": tuple[int, ...],
       "global_dim": int, "kernel_size": int, "encoder_norm": str,
       "use_image_pair": bool, "encoder_coordinates": bool, "flow_scale": float,
       "encoder_params": the encoder's parameters, variables["params"]["global_encoder"]}:
      `fit_pose_probe(train, test, steps=..., **options)` rebuilds the same encoder and
      feeds it the same inputs, so that its g is the model's. The model's `global_norm`
      (a fixed affine map of g at test time) is left out: the probe standardises g
      itself.

    Raises:
      ValueError: the model is not a GlobalLocal, computes g without an encoder
        (use_global_module False, global_source "pose"), or gives its encoder no flow
        (use_flow False; the probe always does); or the variables hold no encoder.
    """
    if not isinstance(model, model_lib.GlobalLocal):
        raise ValueError(
            f"the pose probe reads the global encoder of a GlobalLocal model, got "
            f"{type(model).__name__}"
        )
    if not model.use_global_module or model.global_source != "encoder":
        raise ValueError(
            "the model has no global encoder to probe (use_global_module="
            f"{model.use_global_module}, global_source={model.global_source!r})"
        )
    if not model.use_flow:
        raise ValueError(
            "the model's global encoder sees the image pair without the flow (use_flow=False); "
            "the probe feeds it the flow"
        )
    encoder_params = variables.get("params", {}).get("global_encoder")
    if encoder_params is None:
        raise ValueError("the variables hold no params['global_encoder']")
    return {
        "encoder_channels": tuple(model.encoder_channels),
        "encoder_strides": tuple(model.encoder_strides),
        "global_dim": model.global_dim,
        "kernel_size": model.kernel_size,
        "encoder_norm": model.encoder_norm,
        "use_image_pair": model.use_image_pair,
        "encoder_coordinates": model.encoder_coordinates,
        "flow_scale": model.flow_scale,
        "encoder_params": encoder_params,
    }


def _checked_encoder_params(encoder: nn.Module, encoder_params: Any, encoder_inputs) -> Any:
    """`encoder_params` as jax arrays, after checking that they fit `encoder` exactly."""
    expected = jax.eval_shape(encoder.init, jax.random.key(0), encoder_inputs)["params"]

    def shapes(tree) -> dict[str, tuple[int, ...]]:
        leaves = jax.tree_util.tree_flatten_with_path(tree)[0]
        return {jax.tree_util.keystr(path): tuple(np.shape(leaf)) for path, leaf in leaves}

    if shapes(encoder_params) != shapes(expected):
        raise ValueError(
            f"encoder_params do not fit the probe's encoder {encoder}: parameter shapes "
            f"{shapes(encoder_params)}, expected {shapes(expected)} (are the encoder options "
            "those of the model they come from? see pretrained_global_encoder)"
        )
    return jax.tree_util.tree_map(jnp.asarray, encoder_params)


def _pose_probe_fitter(
    train_source: Sequence[Any],
    test_source: Sequence[Any],
    *,
    steps: int,
    standardise_global_params: bool = True,
    statistics_batches: int = 8,
    encoder_channels: Sequence[int] = (16, 32, 64, 128, 256),
    encoder_strides: Sequence[int] = (2, 2, 2, 2, 1),
    global_dim: int = 6,
    kernel_size: int = 3,
    encoder_norm: str = "none",
    use_image_pair: bool = True,
    encoder_coordinates: bool = False,
    flow_scale: float = 10.0,
    flow_source: str = "gt",
    batch_size: int = 16,
    learning_rate: float = 1e-3,
    warmup_steps: int = 50,
    seed: int = 0,
    hidden: Sequence[int] = (256, 256),
) -> Callable[[Any, bool], dict[str, Any]]:
    """The training and scoring of `fit_pose_probe` (its options and their defaults), as
    fit(encoder_params, train_encoder): fits with the same options reuse one compilation
    of each step."""

    if standardise_global_params and statistics_batches < 1:
        raise ValueError(f"statistics_batches must be >= 1, got {statistics_batches}")
    encoder = GlobalEncoder(
        channels=tuple(encoder_channels),
        strides=tuple(encoder_strides),
        global_dim=global_dim,
        kernel_size=kernel_size,
        norm=encoder_norm,
    )
    head = PoseMLP(hidden=tuple(hidden))
    scale = model_lib.POSE_ROTATION_SCALE

    # What the encoder and the targets read; the pipeline drops the rest before augmenting.
    keys = ("flow", "rotation", "translation") + (("image1", "image2") if use_image_pair else ())

    def inputs(batch):
        flow = layers.normalise_flow(jnp.asarray(batch["flow"])) * flow_scale
        image1, image2 = batch.get("image1"), batch.get("image2")  # absent without the pair
        stacked = layers.global_module_inputs(image1, image2, flow, use_image_pair)
        return layers.with_coordinates(stacked) if encoder_coordinates else stacked

    def targets(batch):
        rotation = rotation_vector(np.asarray(batch["rotation"])) * scale
        return jnp.asarray(np.concatenate([rotation, batch["translation"]], -1), jnp.float32)

    def predict(params, statistics, encoder_inputs):
        global_params = encoder.apply({"params": params["encoder"]}, encoder_inputs)
        standardised = (global_params - statistics["mean"]) / statistics["std"]
        return head.apply({"params": params["head"]}, standardised)

    optimizer = state.make_optimizer(
        learning_rate, "cosine", steps=steps, warmup_steps=warmup_steps
    )
    encode = jax.jit(encoder.apply)
    forward = jax.jit(predict)

    # A frozen encoder is passed in `frozen`, not differentiated: it gets no gradient, no
    # optimiser state, and is not returned. (One compilation per split of the params.)
    @jax.jit
    def step(trained, frozen, opt_state, statistics, encoder_inputs, pose_targets):
        def loss_fn(trained):
            predicted = predict({**frozen, **trained}, statistics, encoder_inputs)
            return jnp.mean(jnp.abs(predicted - pose_targets))

        grads = jax.grad(loss_fn)(trained)
        updates, opt_state = optimizer.update(grads, opt_state, trained)
        return optax.apply_updates(trained, updates), opt_state

    def fit(encoder_params: Any, train_encoder: bool) -> dict[str, Any]:
        stream = iter(
            input_pipeline.train_dataset(
                train_source,
                batch_size=batch_size,
                seed=seed,
                gt_pixels=1,
                flow_source=flow_source,
                keys=keys,
            )
        )
        # The statistics' batches are the first training batches: the data order is the
        # same with and without standardisation.
        peeked = list(
            itertools.islice(stream, statistics_batches if standardise_global_params else 1)
        )
        key_encoder, key_head = jax.random.split(jax.random.key(seed))
        if encoder_params is None:
            encoder_params = encoder.init(key_encoder, inputs(peeked[0]))["params"]
        else:
            encoder_params = _checked_encoder_params(encoder, encoder_params, inputs(peeked[0]))
        # A Dense layer's initial weights depend on the input's width only.
        head_params = head.init(key_head, jnp.zeros((1, global_dim), jnp.float32))["params"]
        if standardise_global_params:
            initial_global_params = np.concatenate(
                [
                    np.asarray(encode({"params": encoder_params}, inputs(batch)), np.float64)
                    for batch in peeked
                ]
            )
            mean = initial_global_params.mean(0)
            std = np.maximum(initial_global_params.std(0), 1e-8)
        else:
            mean, std = np.zeros(global_dim), np.ones(global_dim)
        statistics = {"mean": jnp.asarray(mean, jnp.float32), "std": jnp.asarray(std, jnp.float32)}

        params = {"encoder": encoder_params, "head": head_params}
        trainable = ("encoder", "head") if train_encoder else ("head",)
        trained = {name: params[name] for name in trainable}
        frozen = {name: value for name, value in params.items() if name not in trainable}
        opt_state = optimizer.init(trained)
        for batch in itertools.islice(itertools.chain(peeked, stream), steps):
            trained, opt_state = step(
                trained, frozen, opt_state, statistics, inputs(batch), targets(batch)
            )
        params = {**frozen, **trained}

        predicted, truth, ids = [], [], []
        for batch in input_pipeline.eval_batches(
            test_source, batch_size=batch_size, flow_source=flow_source, keys=keys
        ):
            rows = np.flatnonzero(np.asarray(batch["example_mask"], bool))
            predicted.append(
                np.asarray(forward(params, statistics, inputs(batch)), np.float64)[rows]
            )
            truth.append(np.asarray(targets(batch), np.float64)[rows])
            ids.extend(np.asarray(batch["id"])[rows].tolist())
        predicted, truth = np.concatenate(predicted), np.concatenate(truth)
        predicted[:, :3] /= scale
        truth[:, :3] /= scale
        mean_pose = np.broadcast_to(truth.mean(0), truth.shape)
        translation = predicted[:, 3:]
        return {
            "probe": _pose_errors(predicted, truth),
            "mean_pose": _pose_errors(mean_pose, truth),
            "predicted": {
                "ids": np.asarray(ids),
                "rotation": np.asarray(geometry.rotation_matrix(predicted[:, :3]), np.float64),
                "translation": translation
                / np.maximum(np.linalg.norm(translation, axis=-1, keepdims=True), 1e-12),
            },
            "params": params,
            "global_params_statistics": {"mean": mean, "std": std},
        }

    return fit


def fit_pose_probe(
    train_source: Sequence[Any],
    test_source: Sequence[Any],
    *,
    steps: int,
    encoder_params: Any = None,
    train_encoder: bool = True,
    **options: Any,
) -> dict[str, Any]:
    """The paper's pose probe (Sec. 4.4): a `PoseMLP` on the global module's output g,
    trained to regress the relative pose, with the encoder trained or frozen.

    The encoder (a `GlobalEncoder` fed as in `gld.models.global_local.GlobalLocal`: the
    image pair and
    the normalised flow times `flow_scale`) starts from `encoder_params` or a random
    initialisation; the MLP always starts from a random one. Both are trained (or the
    MLP alone, with `train_encoder=False`) on augmented training batches, on the L1
    error of [10 x the rotation vector, the translation direction], with Adam, warm-up
    and cosine decay (`gld.runs.state.make_optimizer`, as the trainers). The test pairs are
    scored in degrees.

    With `standardise_global_params`, the MLP reads g standardised per dimension with
    fixed statistics: the mean and std of the initial encoder's g over the first
    `statistics_batches` training batches, computed once before training and kept as
    they are while the encoder trains. A randomly initialised encoder's g varies by ~0.005
    across pairs, which would starve the MLP of a signal for a reason that has nothing
    to do with what the encoder knows; standardising the same way in every setting
    puts scratch and pretrained encoders on one footing.

    Args:
      train_source, test_source: random-access records of the splits.
      steps: training steps (> warmup_steps).
      encoder_params: the encoder's initial parameters (e.g. `pretrained_global_encoder`'s
        "encoder_params"; their shapes must fit the encoder options); None draws them
        with `seed`.
      train_encoder: False freezes the encoder: only the MLP's parameters are updated.
      **options: keyword options, with the defaults of `_pose_probe_fitter` (the
        paper's encoder):
      standardise_global_params: standardise g as described above (False: the MLP reads
        g as it is, as `train_encoder_on_pose` does).
      statistics_batches: training batches the standardisation's statistics come from.
      encoder_channels, encoder_strides, global_dim, kernel_size, encoder_norm,
        use_image_pair, encoder_coordinates, flow_scale: the encoder and its inputs, as
        the GlobalLocal options of the same names.
      flow_source: the flow the encoder is given ("gt" or "estimated").
      batch_size: training and evaluation batch size.
      learning_rate, warmup_steps: the peak Adam rate and its linear warm-up.
      seed: initialisation (encoder and MLP) and training data order.
      hidden: the MLP's hidden widths.

    Returns:
      {"probe": {"rotation_deg", "translation_deg"}: mean errors (degrees) of the
         predicted pose on the test pairs,
       "mean_pose": {"rotation_deg", "translation_deg"}: the same for the test pairs'
         mean pose,
       "predicted": {"ids": [N] str, the test pairs' ids in split order,
                     "rotation": [N, 3, 3] float64 rotation matrices,
                     "translation": [N, 3] float64 unit translation directions}: the
         predicted relative pose (X2 = R X1 + t) of every test pair,
       "params": {"encoder": ..., "head": ...}: the parameter trees after training
         (the encoder's as `encoder_params`; a frozen one is bit-identical to them),
       "global_params_statistics": {"mean": [G], "std": [G]} float64: the fixed
         standardisation of g (0 and 1 without it)}.
    """
    fit = _pose_probe_fitter(train_source, test_source, steps=steps, **options)
    return fit(encoder_params, train_encoder)


def pose_probe_settings(
    train_source: Sequence[Any],
    test_source: Sequence[Any],
    *,
    pretrained: dict[str, Any],
    steps: int,
    settings: Sequence[str] = tuple(POSE_PROBE_SETTINGS),
    **options: Any,
) -> dict[str, Any]:
    """The paper's pose table (Sec. 4.4) for one trained model: `fit_pose_probe` in the
    four settings of `POSE_PROBE_SETTINGS` (or those named in `settings`), the encoder
    random ("scratch") or the model's ("pretrained"), frozen ("mlp") or trained with the
    MLP ("full").

    Every setting has the same encoder architecture and inputs, MLP initialisation,
    training batches in the same order, steps, optimiser and standardisation of g (see
    `fit_pose_probe`); the two scratch settings start from the same random encoder.

    Args:
      train_source, test_source: random-access records of the splits.
      pretrained: `pretrained_global_encoder(model, variables)` of the trained model.
      steps: training steps of each setting.
      settings: the settings to run (e.g. the pretrained ones only, for a second model).
      **options: statistics_batches, flow_source, batch_size, learning_rate,
        warmup_steps, seed, hidden, as in `fit_pose_probe` (the encoder's options come
        from `pretrained`, and g is always standardised).

    Returns:
      {each setting of `settings` ("scratch_mlp", "pretrained_mlp", ...):
         {"rotation_deg", "translation_deg"}, mean errors (degrees) on the test pairs,
       "mean_pose": {"rotation_deg", "translation_deg"} of the test pairs' mean pose,
       "predicted": {setting: {"ids": [N] str, "rotation": [N, 3, 3] float64,
         "translation": [N, 3] float64}}, each setting's predicted poses
         (`fit_pose_probe`'s "predicted")}.
    """
    unknown = sorted(set(settings) - set(POSE_PROBE_SETTINGS))
    if unknown or not settings:
        raise ValueError(f"settings must be among {list(POSE_PROBE_SETTINGS)}, got {settings}")
    missing = [name for name in (*ENCODER_OPTIONS, "encoder_params") if name not in pretrained]
    if missing:
        raise ValueError(
            f"pretrained lacks {missing}: pass pretrained_global_encoder(model, variables)"
        )
    fixed = sorted(set(options) & {*ENCODER_OPTIONS, "standardise_global_params"})
    if fixed:
        raise ValueError(f"{fixed} are fixed by the pretrained model and the settings")
    fit = _pose_probe_fitter(
        train_source,
        test_source,
        steps=steps,
        standardise_global_params=True,
        **{name: pretrained[name] for name in ENCODER_OPTIONS},
        **options,
    )
    results: dict[str, Any] = {}
    predicted = {}
    for setting in settings:
        from_pretrained, train_encoder = POSE_PROBE_SETTINGS[setting]
        fitted = fit(pretrained["encoder_params"] if from_pretrained else None, train_encoder)
        results[setting] = fitted["probe"]
        predicted[setting] = fitted["predicted"]
    # The same test pairs in every setting: the last one's mean pose is all of theirs.
    return {**results, "mean_pose": fitted["mean_pose"], "predicted": predicted}


def train_encoder_on_pose(
    train_source: Sequence[Any],
    test_source: Sequence[Any],
    *,
    steps: int,
    encoder_norm: str = "none",
    use_image_pair: bool = True,
    encoder_coordinates: bool = False,
    flow_source: str = "gt",
    flow_scale: float = 10.0,
    batch_size: int = 16,
    learning_rate: float = 1e-3,
    warmup_steps: int = 50,
    seed: int = 0,
    encoder_channels: Sequence[int] = (16, 32, 64, 128, 256),
    hidden: Sequence[int] = (256, 256),
) -> dict[str, dict[str, float]]:
    """How fast can the global encoder learn the relative pose when told it? A capacity
    check, not a depth model: `fit_pose_probe` from a random encoder, trained with the
    MLP, on g as it is (not standardised, as this check was first measured).

    Returns:
      {"encoder": {...}, "mean_pose": {...}}: mean rotation and translation-direction
      errors (degrees) on the test pairs of the trained encoder and of the test pairs'
      mean pose.
    """
    fitted = fit_pose_probe(
        train_source,
        test_source,
        steps=steps,
        train_encoder=True,
        standardise_global_params=False,
        encoder_channels=encoder_channels,
        encoder_norm=encoder_norm,
        use_image_pair=use_image_pair,
        encoder_coordinates=encoder_coordinates,
        flow_scale=flow_scale,
        flow_source=flow_source,
        batch_size=batch_size,
        learning_rate=learning_rate,
        warmup_steps=warmup_steps,
        seed=seed,
        hidden=hidden,
    )
    return {"encoder": fitted["probe"], "mean_pose": fitted["mean_pose"]}
