"""The pose probe on the global encoder itself: how much of the camera motion a global
encoder holds, or can learn, trained with a pose-regressing MLP on top.

    errors, predicted = fit_pose_probe(train, test, encoder_params=..., train_encoder=True)

`fit_pose_probe` trains the MLP (`gld.analysis.probes.PoseMLP`) on the global encoder,
frozen or not, from a trained model's encoder (`pretrained_global_encoder`) or a random
one; `pose_probe_settings` runs the paper's four settings of its pose table (Sec. 4.4)
and keeps each one's predicted poses; `train_encoder_on_pose` trains an encoder on the
true pose alone, a capacity check with no depth (`experiments.encoder_pose`).
"""

from __future__ import annotations

import itertools
from collections.abc import Callable, Sequence
from typing import Any

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
import optax

from gld import geometry, input_pipeline
from gld.analysis.probes import PoseMLP, pose_errors, rotation_vector
from gld.models import global_local as model_lib
from gld.models import layers
from gld.models.global_encoder import GlobalEncoder
from gld.runs.optimizer import make_optimizer

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
    flow_scale: float = layers.FLOW_SCALE,
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
        flow = layers.scaled_flow(jnp.asarray(batch["flow"]), flow_scale)
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

    optimizer = make_optimizer(learning_rate, "cosine", steps=steps, warmup_steps=warmup_steps)
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
            encoder_params = layers.init_once(encoder, key_encoder, inputs(peeked[0]))["params"]
        else:
            encoder_params = _checked_encoder_params(encoder, encoder_params, inputs(peeked[0]))
        # A Dense layer's initial weights depend on the input's width only.
        head_params = layers.init_once(head, key_head, jnp.zeros((1, global_dim), jnp.float32))[
            "params"
        ]
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
            "probe": pose_errors(predicted, truth),
            "mean_pose": pose_errors(mean_pose, truth),
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
    and cosine decay (`gld.runs.optimizer.make_optimizer`, as the trainers). The test pairs are
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
    flow_scale: float = layers.FLOW_SCALE,
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
