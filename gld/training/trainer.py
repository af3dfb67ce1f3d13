"""Training: the pure train step, its sharded compilation, and the training loop.

`make_train_step` builds a pure `train_step(state, batch, rng) -> (state, metrics)`;
`train_and_evaluate` runs it over a mesh of all devices (`gld.sharding`: batch sharded,
state replicated), resumes from and saves to the run's workdir (`gld.runs.workdir`: locked
while training; verified orbax checkpoints of the state and the grain iterator,
`config.json`, metrics), and evaluates periodically (`gld.evaluation.evaluate`). The same code
runs on one CPU, on fake CPU devices, on a GPU and on several processes after
`jax.distributed.initialize`.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import flax.linen as nn
import jax
import jax.numpy as jnp
import optax
from jax.experimental import multihost_utils
from jax.sharding import Mesh

from gld import input_pipeline, sharding
from gld.evaluation import evaluate as evaluation
from gld.evaluation import metrics
from gld.flow_pose import FLOW_POSE_KEYS
from gld.losses import photometric
from gld.losses import supervised as losses
from gld.models import layers, registry
from gld.runs import checkpoints as checkpoint_lib
from gld.runs import metrics_log, trained_flow
from gld.runs import workdir as workdir_lib
from gld.runs.config import TrainConfig, config_optimizer
from gld.runs.state import TrainState, create_train_state

# Keys of a batch that the train step reads (the rest, like "id", stay on the host).
TRAIN_KEYS = ("image1", "image2", "flow", "depth", "sparse_mask")
# Training losses by the name a model class gives as `LOSS` (default "supervised"), and
# the batch keys each reads: the self-supervised loss sees no depth, only the cameras.
LOSSES = {"supervised": losses.total_loss, "self_supervised": photometric.self_supervised_loss}
LOSS_KEYS = {
    "supervised": TRAIN_KEYS,
    "self_supervised": ("image1", "image2", "flow", "intrinsics1", "intrinsics2"),
}


def loss_name(model: nn.Module) -> str:
    """The training loss a model is trained with (`LOSSES`)."""
    return getattr(model, "LOSS", "supervised")


def batch_keys(model: nn.Module, loss_weights=None) -> tuple[str, ...]:
    """The batch keys a model's train step reads: its loss's (the intrinsics too with an
    epipolar term, the pose from the flow with a pose teacher) and its own inputs."""
    keys = LOSS_KEYS[loss_name(model)]
    if getattr(loss_weights, "epipolar", 0) > 0:
        keys += ("intrinsics1", "intrinsics2")
    if getattr(loss_weights, "pose_teacher", 0) > 0:
        keys += FLOW_POSE_KEYS
    return layers.with_input_keys(model, keys)


class NonFiniteLossError(RuntimeError):
    """The loss became NaN or inf; the last good checkpoint is kept."""


def make_train_step(
    *,
    model: nn.Module,
    optimizer: optax.GradientTransformation,
    loss_weights: losses.LossWeights | photometric.SelfSupervisedWeights,
) -> Callable[[TrainState, dict, jax.Array], tuple[TrainState, dict]]:
    """Builds the pure `train_step(state, batch, rng) -> (state, metrics)`; the loss is
    the model's (`loss_name`): the sparse supervised loss, or the self-supervised one."""
    loss_function = LOSSES[loss_name(model)]

    def train_step(state: TrainState, batch: dict, rng: jax.Array):
        has_batch_stats = bool(state.batch_stats)

        def loss_fn(params):
            variables = {"params": params}
            if has_batch_stats:
                variables["batch_stats"] = state.batch_stats
            outputs = layers.apply_model(
                model,
                variables,
                batch,
                train=True,
                rngs={"dropout": rng},
                mutable=["batch_stats"] if has_batch_stats else False,
            )
            outputs, updates = outputs if has_batch_stats else (outputs, {})
            loss, terms = loss_function(outputs, batch, loss_weights)
            return loss, (terms, updates.get("batch_stats", state.batch_stats))

        (_, (terms, batch_stats)), grads = jax.value_and_grad(loss_fn, has_aux=True)(state.params)
        updates, opt_state = optimizer.update(grads, state.opt_state, state.params)
        params = optax.apply_updates(state.params, updates)
        step_metrics = dict(terms)
        step_metrics["grad_norm"] = optax.global_norm(grads)
        step_metrics["learning_rate"] = jnp.asarray(
            opt_state.hyperparams["learning_rate"] if hasattr(opt_state, "hyperparams") else jnp.nan
        )
        new_state = state.replace(
            step=state.step + 1, params=params, batch_stats=batch_stats, opt_state=opt_state
        )
        return new_state, step_metrics

    return train_step


def jit_train_step(train_step: Callable, mesh: Mesh) -> Callable:
    """`train_step` compiled with replicated state, sharded batch and donated state."""
    jitted = jax.jit(
        train_step,
        in_shardings=(
            sharding.replicated(mesh),
            sharding.batch_sharded(mesh),
            sharding.replicated(mesh),
        ),
        out_shardings=(sharding.replicated(mesh), sharding.replicated(mesh)),
        donate_argnums=0,
    )
    return sharding.under_mesh(jitted, mesh)


def train_and_evaluate(
    config: TrainConfig,
    workdir: str | Path,
    train_source,
    test_source=None,
    *,
    progress: bool = True,
    print_fn: Callable[[str], None] = print,
    records: Mapping[str, str] | None = None,
) -> TrainState:
    """Trains (resuming from the workdir's newest intact checkpoint) and evaluates
    periodically.

    Everything is checked before anything is written into the workdir: the options,
    the model, optimiser and state, the workdir's stored config, the lock, the
    checkpoints. Then `config.json` and `records` are written atomically: on a new
    workdir before the first step, on an existing one with the first checkpoint this
    launch saves, if anything differs (the rule, and config.json's "history" of changed
    options, are in `gld.runs.workdir`). The changed options are printed at every launch.

    Args:
      config: the run.
      workdir: where checkpoints, logs and evaluations go.
      train_source, test_source: random-access record sources (TFDS data sources).
      progress: show a progress bar with step rate and ETA.
      print_fn: where start-up information and checkpoint warnings go.
      records: extra text files for the workdir, name -> content (e.g. the launcher's
        {"flags.txt": ...}), written with config.json.

    Returns:
      The final TrainState.

    Raises:
      ValueError: a bad option or record name, or a workdir holding another architecture
        or dataset (nothing is written).
      WorkdirLockedError: another process is training in the workdir (it is named).
      CorruptCheckpointError: the workdir has checkpoints but none is intact.
      NonFiniteLossError: the loss became NaN/inf (the step is named; nothing is saved).
    """
    workdir = Path(workdir)
    if hasattr(config, "validate"):
        config.validate()
    records = workdir_lib.check_records(records)
    mesh = sharding.make_mesh()
    local_batch = sharding.per_process_batch_size(config.batch_size, mesh)
    model = registry.make_model(config.model, **config.model_config)
    optimizer = config_optimizer(config)
    workdir_lib.check_run_config(workdir, config)
    state = create_train_state(model, optimizer, config.height, config.width, config.seed)
    state = _with_pretrained(model, state, workdir, print_fn)
    if jax.process_index() == 0:
        for name, count in registry.parameter_counts(state.params).items():
            print_fn(f"parameters {name}: {count:,}")

    dataset = input_pipeline.train_dataset(
        train_source,
        batch_size=local_batch,
        seed=config.seed,
        gt_pixels=config.gt_pixels,
        flow_source=config.flow_source,
        augment=config.augment,
        fixed_sparse_pixels=config.fixed_sparse_pixels,
        worker_count=config.worker_count,
        keys=batch_keys(model, config.loss_weights()),
        process_index=jax.process_index(),
        process_count=jax.process_count(),
    )
    iterator = iter(dataset)
    # The stored config is read again under the lock: the previous holder may have changed it.
    with workdir_lib.held_run(
        workdir, config.keep_checkpoints, lambda: workdir_lib.check_run_config(workdir, config)
    ) as (changes, manager):
        return _train(
            config,
            workdir,
            state,
            iterator,
            manager,
            changes=changes,
            records=records,
            model=model,
            optimizer=optimizer,
            mesh=mesh,
            test_source=test_source,
            progress=progress,
            print_fn=print_fn,
        )


def _with_pretrained(
    model: nn.Module, state: TrainState, workdir: Path, print_fn: Callable[[str], None]
) -> TrainState:
    """A new run of a model with a pretrained flow network (`gld.models.flow_depth`'s
    `flow_net_workdir`) starts from it; a run with checkpoints restores its own (the
    pretrained run need not exist any more)."""
    flow_net_workdir = getattr(model, "flow_net_workdir", "")
    if not flow_net_workdir or any((workdir / checkpoint_lib.CHECKPOINTS_DIR).glob("[0-9]*")):
        return state
    loaded = trained_flow.load_pretrained_flow(state.params, flow_net_workdir)
    if loaded is None:
        return state
    params, note = loaded
    if jax.process_index() == 0:
        print_fn(note)
    return state.replace(params=params)


def resume(
    workdir: Path, manager, state: TrainState, iterator, print_fn: Callable[[str], None]
) -> TrainState:
    """The newest intact checkpoint restored into `state` and `iterator` (or `state` on a
    new run); damaged newer checkpoints are moved aside so their steps can be saved again
    (every trainer resumes so)."""
    if manager.latest_step() is None:
        return state
    restored = checkpoint_lib.restore_intact_checkpoint(manager, state, iterator, print_fn=print_fn)
    print_fn(f"resumed from step {restored.step} in {workdir / 'checkpoints'}")
    if restored.skipped:
        if jax.process_count() > 1:
            # Every process restores before process 0 moves anything.
            multihost_utils.sync_global_devices("gld: checkpoints restored")
        if jax.process_index() == 0:
            for moved in checkpoint_lib.move_aside(workdir, manager, restored.skipped):
                print_fn(f"damaged checkpoint moved to {moved}")
        if jax.process_count() > 1:
            multihost_utils.sync_global_devices("gld: damaged checkpoints moved")
            manager.reload()
    return restored.state


def _train(
    config: TrainConfig,
    workdir: Path,
    state: TrainState,
    iterator,
    manager,
    *,
    changes: dict | None,
    records: dict[str, str],
    model: nn.Module,
    optimizer: optax.GradientTransformation,
    mesh: Mesh,
    test_source,
    progress: bool,
    print_fn: Callable[[str], None],
) -> TrainState:
    """The depth trainer in a workdir it holds: resume, the run's records, `run_loop`."""
    state = resume(workdir, manager, state, iterator, print_fn)
    start_step = int(jax.device_get(state.step))
    will_train = start_step < config.steps
    # On a new workdir the records are written now; on an existing one with the first
    # checkpoint of this launch, so that they never describe steps not trained.
    records_pending = False
    if changes is None:
        workdir_lib.write_run_config(workdir, config, step=start_step, records=records)
    else:
        if changes and jax.process_index() == 0:
            when = (
                "stored in config.json with this launch's first checkpoint"
                if will_train
                else f"not stored: no step to train beyond {start_step}"
            )
            print_fn(
                f"options changed since the stored config: "
                f"{workdir_lib.describe_changes(changes)} ({when})"
            )
        records_pending = bool(changes) or workdir_lib.records_differ(workdir, records)

    def after_checkpoint() -> None:
        nonlocal records_pending
        if records_pending:
            workdir_lib.write_run_config(workdir, config, step=start_step, records=records)
            records_pending = False

    eval_step = evaluation.jit_eval_step(evaluation.make_eval_step(model=model), mesh)

    def evaluate(state: TrainState) -> tuple[dict[str, float], str]:
        per_example, _ = evaluation.evaluate_source(
            model,
            state.variables(),
            test_source,
            batch_size=config.eval_batch_size,
            flow_source=config.flow_source,
            mesh=mesh,
            max_examples=config.eval_examples,
            eval_step=eval_step,
        )
        summary = metrics.summarise(per_example, per_example.pop("example_mask"))
        message = "test " + ", ".join(
            f"{metrics.METRIC_NAMES[k]} {summary[k]['mean']:.4f}" for k in metrics.DEPTH_METRICS
        )
        return {k: v["mean"] for k, v in summary.items() if k in metrics.DEPTH_METRICS}, message

    train_step = make_train_step(
        model=model, optimizer=optimizer, loss_weights=config.loss_weights()
    )
    return run_loop(
        state,
        iterator,
        manager,
        workdir=workdir,
        mesh=mesh,
        train_step=train_step,
        batch_keys=batch_keys(model, config.loss_weights()),
        schedule=config,
        evaluate=evaluate if test_source is not None else None,
        after_checkpoint=after_checkpoint,
        progress=progress,
        print_fn=print_fn,
    )


def run_loop(
    state: TrainState,
    iterator,
    manager,
    *,
    workdir: Path,
    mesh: Mesh,
    train_step: Callable,
    batch_keys: Sequence[str],
    schedule: Any,
    evaluate: Callable[[TrainState], tuple[dict[str, float], str]] | None,
    after_checkpoint: Callable[[], None] | None = None,
    progress: bool,
    description: str = "train",
    postfix: str = "loss",
    print_fn: Callable[[str], None],
) -> TrainState:
    """The training loop of every trainer (depth and flow), in a workdir it holds.

    Steps `state` from its step to `schedule.steps` with the pure `train_step(state,
    batch, rng) -> (state, metrics)` (compiled here over `mesh`; its metrics hold
    "loss") on the `batch_keys` of `iterator`'s batches, with the key of each step
    folded from the state's base key. Every `log_every` steps (and at the end) the
    metrics go to metrics.jsonl and TensorBoard, with the step rate; every
    `checkpoint_every` steps the state and the iterator are saved (then
    `after_checkpoint()` runs); every `eval_every` steps `evaluate(state)` returns the
    test values to log and a line to show. Lines logged after the starting step by an
    earlier launch are dropped first.

    Args:
      schedule: anything with the int attributes steps, batch_size, log_every,
        checkpoint_every and eval_every (a TrainConfig, a FlowTrainConfig).
      description, postfix: the progress bar's label and the metric it shows.

    Raises:
      NonFiniteLossError: the loss became NaN/inf (the step is named; the last good
        checkpoint is kept).
    """
    start_step = int(jax.device_get(state.step))
    if jax.process_index() == 0:
        dropped = metrics_log.drop_metrics_after(workdir, start_step)
        if dropped:
            print_fn(f"metrics.jsonl: dropped {dropped} lines after step {start_step}")
    state = jax.device_put(state, sharding.replicated(mesh))
    train_step = jit_train_step(train_step, mesh)
    logger = metrics_log.MetricsLogger(workdir)
    base_rng = jax.random.wrap_key_data(jnp.asarray(jax.device_get(state.rng)))
    steps = schedule.steps

    def due(every: int, done: int) -> bool:
        return bool(every) and (done % every == 0 or done == steps)

    bar = None
    if progress and jax.process_index() == 0:
        from tqdm import tqdm

        bar = tqdm(
            total=steps, initial=start_step, desc=description, unit="step", dynamic_ncols=True
        )
    window_start, window_steps = time.perf_counter(), 0
    pending: tuple[int, dict] | None = None
    try:
        for step in range(start_step, steps):
            batch = sharding.to_global_batch(next(iterator), mesh, batch_keys)
            state, step_metrics = train_step(state, batch, jax.random.fold_in(base_rng, step))
            # Check the previous step's loss while this one runs (keeps dispatch async).
            if pending is not None:
                _raise_if_not_finite(*pending)
            pending = (step + 1, step_metrics)
            window_steps += 1
            done = step + 1
            if bar is not None:
                bar.update(1)
            if due(schedule.log_every, done):
                _raise_if_not_finite(*pending)
                values = {k: float(v) for k, v in jax.device_get(step_metrics).items()}
                elapsed = time.perf_counter() - window_start
                values["steps_per_sec"] = window_steps / max(elapsed, 1e-9)
                values["examples_per_sec"] = values["steps_per_sec"] * schedule.batch_size
                logger.write(done, values)
                if bar is not None:
                    bar.set_postfix({postfix: f"{values[postfix]:.4f}"})
                window_start, window_steps = time.perf_counter(), 0
            if due(schedule.checkpoint_every, done):
                _raise_if_not_finite(*pending)
                checkpoint_lib.save_checkpoint(manager, state, iterator)
                if after_checkpoint is not None:
                    after_checkpoint()
            if evaluate is not None and due(schedule.eval_every, done):
                values, message = evaluate(state)
                logger.write(done, values, prefix="test")
                if bar is not None:
                    bar.write(f"step {done}: {message}")
                else:
                    print_fn(f"step {done}: {message}")
        if pending is not None:
            _raise_if_not_finite(*pending)
    finally:
        if bar is not None:
            bar.close()
        logger.close()
    return state


def _raise_if_not_finite(step: int, step_metrics: dict) -> None:
    loss = float(jax.device_get(step_metrics["loss"]))
    if not math.isfinite(loss):
        raise NonFiniteLossError(
            f"loss is {loss} at step {step}; stopping. The last good checkpoint is kept; "
            "lower --learning_rate or check the data for NaN/inf"
        )
