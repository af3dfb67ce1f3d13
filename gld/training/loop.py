"""The skeleton every trainer runs: set up, take the workdir, resume, loop.

    state = loop.train(DepthRun(config), workdir, train_source, test_source)

A trainer says what is its own as a `TrainingRun` (`gld.training.trainer.DepthRun`,
`gld.training.flow_trainer.FlowRun`): its model, the check of a workdir's stored config,
a fresh state, the data it reads, its train step, its evaluation and the records it
writes when it starts. `train` does the rest, the same for every trainer: the options,
the model and optimiser and the workdir's stored config are checked before anything is
written; then the workdir is held (`gld.runs.workdir.held_run`) before the costly
start-up (the fresh state, the data, compiling), so that a second launch is refused at
once; the newest intact checkpoint is restored (`resume`) and `run_loop` steps to the
end, over a mesh of all devices (`gld.sharding`), saving verified checkpoints of the
state and the data iterator, logging metrics and evaluating periodically. A full disk
ends the run with a `gld.files.DiskFullError` naming the workdir; the checkpoints saved
before are kept.
"""

from __future__ import annotations

import abc
import contextlib
import math
import time
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any

import flax.linen as nn
import jax
import jax.numpy as jnp
import optax
from jax.experimental import multihost_utils
from jax.sharding import Mesh

from gld import input_pipeline, sharding
from gld.arguments import RunStoppedError
from gld.files import DiskFullError, no_space_error
from gld.runs import checkpoints as checkpoint_lib
from gld.runs import metrics_log
from gld.runs import workdir as workdir_lib
from gld.runs.state import TrainState
from gld.runs.trainer_options import TrainerOptions

# (test values to log, a line to show) of a periodic evaluation.
Evaluation = Callable[[TrainState], tuple[dict[str, float], str]]


class NonFiniteLossError(RunStoppedError):
    """The loss became NaN or inf; the last good checkpoint is kept."""


class TrainingRun(abc.ABC):
    """What a trainer adds to the skeleton (`train`): one run of it."""

    # The progress bar's label and the step metric it shows.
    description = "train"
    postfix = "loss"

    def __init__(self, config: TrainerOptions):
        self.config = config

    @abc.abstractmethod
    def make_model(self) -> nn.Module:
        """The network, after `config.validate()`."""

    @abc.abstractmethod
    def check_workdir(self, workdir: Path) -> dict[str, tuple] | None:
        """Checks the workdir's stored config, reading only; returns the options that
        differ ({name: (stored, now)}), or None when it stores none. Raises ValueError
        for a workdir holding another run."""

    @abc.abstractmethod
    def fresh_state(
        self,
        model: nn.Module,
        optimizer: optax.GradientTransformation,
        workdir: Path,
        print_fn: Callable[[str], None],
    ) -> TrainState:
        """The state a new run starts from."""

    @abc.abstractmethod
    def parameter_counts(self, state: TrainState) -> dict[str, int]:
        """Parameters by name, shown at start-up."""

    @abc.abstractmethod
    def batch_keys(self, model: nn.Module) -> tuple[str, ...]:
        """The batch keys the train step reads."""

    @abc.abstractmethod
    def data_options(self) -> dict[str, Any]:
        """The trainer's own options of `gld.input_pipeline.train_dataset`."""

    @abc.abstractmethod
    def train_step(self, model: nn.Module, optimizer: optax.GradientTransformation) -> Callable:
        """The pure `train_step(state, batch, rng) -> (state, metrics)`."""

    @abc.abstractmethod
    def evaluation(self, model: nn.Module, mesh: Mesh, test_source) -> Evaluation:
        """The periodic evaluation on `test_source`."""

    @abc.abstractmethod
    def begin(
        self,
        workdir: Path,
        start_step: int,
        changes: dict[str, tuple] | None,
        print_fn: Callable[[str], None],
    ) -> Callable[[], None] | None:
        """Writes the run's records on starting in the workdir it holds (after resuming
        at `start_step`); may return what to run after each checkpoint."""


def train(
    run: TrainingRun,
    workdir: str | Path,
    train_source,
    test_source=None,
    *,
    progress: bool = True,
    print_fn: Callable[[str], None] = print,
    keep_compiled: bool = False,
) -> TrainState:
    """Trains `run` (resuming from the workdir's newest intact checkpoint) and evaluates
    it every `eval_every` steps on `test_source`.

    The options, the model and optimiser and the workdir's stored config are checked
    before anything is written. The workdir is then held (locked, its stored config read
    again under the lock) before the costly start-up: initialising the state, opening the
    data, compiling. A second launch on a held workdir is refused before it builds
    anything. With `keep_compiled`, the programs compiled from then on are kept in the
    workdir (`workdir_lib.keep_compiled_programs`, for the rest of the process).

    Returns:
      The final TrainState.

    Raises:
      ValueError: a bad option, or a workdir holding another run (nothing is written).
      gld.runs.lock.WorkdirLockedError: another process trains in the workdir.
      gld.runs.checkpoints.CorruptCheckpointError: no checkpoint of the workdir is intact.
      NonFiniteLossError: the loss became NaN/inf (the step is named; nothing is saved).
      gld.files.DiskFullError: the disk of the workdir is full (the checkpoints saved
        before are kept).
    """
    workdir = Path(workdir)
    config = run.config
    config.validate()
    mesh = sharding.make_mesh()
    local_batch = sharding.per_process_batch_size(config.batch_size, mesh)
    model = run.make_model()
    optimizer = config.optimizer()
    run.check_workdir(workdir)
    # The stored config is read again under the lock: the previous holder may have changed it.
    with (
        _one_line_when_the_disk_is_full(workdir),
        workdir_lib.held_run(workdir, lambda: run.check_workdir(workdir)) as changes,
    ):
        if keep_compiled:
            workdir_lib.keep_compiled_programs(workdir)
        state = run.fresh_state(model, optimizer, workdir, print_fn)
        if jax.process_index() == 0:
            print_fn(f"devices: {mesh.devices.size} {jax.default_backend()}, batch split over them")
            for name, count in run.parameter_counts(state).items():
                print_fn(f"parameters {name}: {count:,}")
        keys = run.batch_keys(model)
        dataset = input_pipeline.train_dataset(
            train_source,
            batch_size=local_batch,
            seed=config.seed,
            augment=config.augment,
            worker_count=config.worker_count,
            keys=keys,
            process_index=jax.process_index(),
            process_count=jax.process_count(),
            **run.data_options(),
        )
        iterator = iter(dataset)
        with checkpoint_lib.saving_manager(workdir, keep=config.keep_checkpoints) as manager:
            state = resume(workdir, manager, state, iterator, print_fn)
            start_step = int(jax.device_get(state.step))
            after_checkpoint = run.begin(workdir, start_step, changes, print_fn)
            return run_loop(
                state,
                iterator,
                manager,
                workdir=workdir,
                mesh=mesh,
                train_step=run.train_step(model, optimizer),
                batch_keys=keys,
                schedule=config,
                evaluate=(
                    run.evaluation(model, mesh, test_source) if test_source is not None else None
                ),
                after_checkpoint=after_checkpoint,
                progress=progress,
                description=run.description,
                postfix=run.postfix,
                print_fn=print_fn,
            )


@contextlib.contextmanager
def _one_line_when_the_disk_is_full(workdir: Path) -> Iterator[None]:
    """A write into `workdir` that finds its disk full, however orbax or another writer
    wrapped the error, ends the run with a `DiskFullError` saying what is kept."""
    try:
        yield
    except Exception as error:
        if isinstance(error, DiskFullError) or no_space_error(error) is None:
            raise
        newest = checkpoint_lib.last_checkpointed_step(workdir)
        kept = (
            f"the checkpoints saved before are kept (newest: step {newest})"
            if newest
            else "no checkpoint was saved yet"
        )
        raise DiskFullError(
            f"disk full: no space left to write in {workdir}; {kept}. Free space, then "
            "relaunch the same command to resume"
        ) from None


def resume(
    workdir: Path, manager, state: TrainState, iterator, print_fn: Callable[[str], None]
) -> TrainState:
    """The newest intact checkpoint restored into `state` and `iterator` (or `state` on a
    new run); damaged newer checkpoints are moved aside so their steps can be saved again."""
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


def jit_train_step(train_step: Callable, mesh: Mesh, state_sharding: Any) -> Callable:
    """`train_step` compiled with the state placed by `state_sharding` (a tree of
    shardings like the state's, `sharding.state_sharding`), the batch sharded and the
    state donated."""
    jitted = jax.jit(
        train_step,
        in_shardings=(
            state_sharding,
            sharding.batch_sharded(mesh),
            sharding.replicated(mesh),
        ),
        out_shardings=(state_sharding, sharding.replicated(mesh)),
        donate_argnums=0,
    )
    return sharding.under_mesh(jitted, mesh)


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
    placement = sharding.state_sharding(state, mesh)
    state = jax.device_put(state, placement)
    train_step = jit_train_step(train_step, mesh, placement)
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
