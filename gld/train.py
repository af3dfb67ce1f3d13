"""Training: state, jit-compiled data-parallel steps, checkpointing and the training loop.

The step functions are pure (`make_train_step`, `make_eval_step`); the loop
(`train_and_evaluate`) runs them over a `Mesh` of all devices with the batch sharded on
"data" and the state replicated, checkpoints with orbax (state and the grain iterator),
and logs to `metrics.jsonl` and TensorBoard. The same code runs on one CPU, on fake CPU
devices, on a GPU and on several processes after `jax.distributed.initialize`.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import math
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import flax
import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
import optax
import orbax.checkpoint as ocp
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from gld import input_pipeline, losses, metrics
from gld import model as model_lib
from gld.hypernet import BATCH_AXIS

# Keys of a batch that go to the devices (the rest, like "id", stay on the host).
TRAIN_KEYS = ("image1", "image2", "flow", "depth", "sparse_mask")
EVAL_KEYS = ("image1", "image2", "flow", "depth", "depth_valid", "example_mask")


class NonFiniteLossError(RuntimeError):
    """The loss became NaN or inf; the last good checkpoint is kept."""


@flax.struct.dataclass
class TrainState:
    """Everything a training run needs to continue exactly where it stopped."""

    step: jax.Array
    params: Any
    batch_stats: Any
    opt_state: Any
    rng: jax.Array  # raw key data of the run's base PRNG key

    def variables(self) -> dict[str, Any]:
        """The model variables for `model.apply`."""
        if self.batch_stats:
            return {"params": self.params, "batch_stats": self.batch_stats}
        return {"params": self.params}


@dataclasses.dataclass
class TrainConfig:
    """A training run, as plain values (the launcher turns flags into this)."""

    model: str = "global_local"
    model_config: dict[str, Any] = dataclasses.field(default_factory=dict)
    batch_size: int = 16  # global, over all processes and devices
    steps: int = 94_000
    learning_rate: float = 1e-4
    lr_schedule: str = "constant"  # "constant" (the paper) or "cosine" (warm-up, decay)
    warmup_steps: int = 0
    depth_weight: float = 5.0
    smoothness_weight: float = 2.0
    gt_pixels: int = 1  # supervised pixels per image; 0 = dense
    fixed_sparse_pixels: bool = False
    flow: str = "estimated"  # which flow the model sees: "estimated" or "gt"
    augment: bool = True
    seed: int = 0
    log_every: int = 50
    eval_every: int = 1000
    checkpoint_every: int = 1000
    keep_checkpoints: int = 2
    eval_batch_size: int = 16
    eval_examples: int = 0  # periodic evaluation on the first N test examples; 0 = all
    worker_count: int = 0
    dataset: str = ""
    height: int = 0
    width: int = 0

    def architecture(self) -> dict[str, Any]:
        """What a checkpoint's parameters depend on (a workdir refuses other values)."""
        speed_only = {"filter_formulation"}  # changes how, not what, the model computes
        full = model_lib.full_config(self.model, self.model_config)
        config = {k: v for k, v in full.items() if k not in speed_only}
        return {"model": self.model, **dict(sorted(config.items()))}

    def loss_weights(self) -> losses.LossWeights:
        return losses.LossWeights(depth=self.depth_weight, smoothness=self.smoothness_weight)


# --------------------------------------------------------------------------- state & steps


def dummy_batch(batch_size: int, height: int, width: int) -> dict[str, np.ndarray]:
    """Zero inputs of the right shapes, for `model.init` and shape checks."""
    return {
        "image1": np.zeros((batch_size, height, width, 3), np.float32),
        "image2": np.zeros((batch_size, height, width, 3), np.float32),
        "flow": np.zeros((batch_size, height, width, 2), np.float32),
    }


def init_variables(model: nn.Module, height: int, width: int, seed: int) -> dict[str, Any]:
    """Initial model variables for images of the given size."""
    batch = dummy_batch(1, height, width)
    return model.init(
        jax.random.key(seed), batch["image1"], batch["image2"], batch["flow"], train=False
    )


def create_train_state(
    model: nn.Module, optimizer: optax.GradientTransformation, height: int, width: int, seed: int
) -> TrainState:
    """A fresh state: initial parameters, optimiser state, step 0, the run's base key."""
    variables = init_variables(model, height, width, seed)
    params = variables["params"]
    return TrainState(
        step=jnp.zeros((), jnp.int32),
        params=params,
        batch_stats=variables.get("batch_stats", {}),
        opt_state=optimizer.init(params),
        rng=jax.random.key_data(jax.random.key(seed + 1)),
    )


LR_SCHEDULES = ("constant", "cosine")


def learning_rate_schedule(
    learning_rate: float, schedule: str = "constant", *, steps: int = 0, warmup_steps: int = 0
) -> optax.Schedule:
    """The learning rate per step.

    "constant" is the paper's. "cosine" rises linearly from 0 over `warmup_steps`, then
    decays along a cosine to 1% of `learning_rate` at `steps`.
    """
    if schedule == "constant":
        return optax.constant_schedule(learning_rate)
    if schedule == "cosine":
        if not 0 <= warmup_steps < steps:
            raise ValueError(
                f"warmup_steps ({warmup_steps}) must be in [0, steps ({steps})) for the "
                "cosine schedule: lower --warmup_steps or use --lr_schedule=constant"
            )
        return optax.warmup_cosine_decay_schedule(
            init_value=0.0,
            peak_value=learning_rate,
            warmup_steps=warmup_steps,
            decay_steps=steps,
            end_value=0.01 * learning_rate,
        )
    raise ValueError(f"lr_schedule must be one of {LR_SCHEDULES}, got {schedule!r}")


def make_optimizer(
    learning_rate: float, schedule: str = "constant", *, steps: int = 0, warmup_steps: int = 0
) -> optax.GradientTransformation:
    """Adam (the paper's optimiser) with the given schedule; the rate is logged."""
    rate = learning_rate_schedule(learning_rate, schedule, steps=steps, warmup_steps=warmup_steps)
    return optax.inject_hyperparams(optax.adam)(learning_rate=rate)


def config_optimizer(config: TrainConfig) -> optax.GradientTransformation:
    """The optimiser of a run."""
    return make_optimizer(
        config.learning_rate,
        config.lr_schedule,
        steps=config.steps,
        warmup_steps=config.warmup_steps,
    )


def make_train_step(
    *,
    model: nn.Module,
    optimizer: optax.GradientTransformation,
    loss_weights: losses.LossWeights,
) -> Callable[[TrainState, dict, jax.Array], tuple[TrainState, dict]]:
    """Builds the pure `train_step(state, batch, rng) -> (state, metrics)`."""

    def train_step(state: TrainState, batch: dict, rng: jax.Array):
        has_batch_stats = bool(state.batch_stats)

        def loss_fn(params):
            variables = {"params": params}
            if has_batch_stats:
                variables["batch_stats"] = state.batch_stats
            outputs = model.apply(
                variables,
                batch["image1"],
                batch["image2"],
                batch["flow"],
                train=True,
                rngs={"dropout": rng},
                mutable=["batch_stats"] if has_batch_stats else False,
            )
            outputs, updates = outputs if has_batch_stats else (outputs, {})
            loss, terms = losses.total_loss(outputs, batch, loss_weights)
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


def make_eval_step(*, model: nn.Module) -> Callable[[dict, dict], dict]:
    """Builds the pure `eval_step(variables, batch) -> per-example metrics` ([B] each).

    The result also carries `example_mask` so padded rows can be dropped exactly.
    """

    def eval_step(variables: dict, batch: dict) -> dict:
        outputs = model.apply(
            variables, batch["image1"], batch["image2"], batch["flow"], train=False
        )
        per_example = metrics.depth_metrics(outputs["depth"], batch["depth"], batch["depth_valid"])
        per_example["example_mask"] = batch["example_mask"] & (per_example["num_pixels"] > 0)
        return per_example

    return eval_step


# --------------------------------------------------------------------------- sharding


def make_mesh(devices: Sequence[jax.Device] | None = None) -> Mesh:
    """A 1-D data-parallel mesh over all devices (of all processes)."""
    devices = np.asarray(devices if devices is not None else jax.devices())
    return Mesh(devices, (BATCH_AXIS,))


def replicated(mesh: Mesh) -> NamedSharding:
    return NamedSharding(mesh, PartitionSpec())


def batch_sharded(mesh: Mesh) -> NamedSharding:
    return NamedSharding(mesh, PartitionSpec(BATCH_AXIS))


def to_global_batch(local_batch: dict[str, np.ndarray], mesh: Mesh, keys: Sequence[str]) -> dict:
    """This process's rows -> global arrays sharded on "data" (batch axis)."""
    sharding = batch_sharded(mesh)
    return {
        key: jax.make_array_from_process_local_data(sharding, np.asarray(local_batch[key]))
        for key in keys
    }


def per_process_batch_size(global_batch_size: int, mesh: Mesh) -> int:
    """Rows each process feeds; the global batch must split evenly over devices."""
    if global_batch_size % mesh.devices.size:
        raise ValueError(
            f"batch_size {global_batch_size} is not divisible by the {mesh.devices.size} devices"
        )
    return global_batch_size // jax.process_count()


def _under_mesh(jitted: Callable, mesh: Mesh) -> Callable:
    """Calls (and so traces) `jitted` with `mesh` set: per-example code that XLA cannot
    partition by itself (the `lax.map` filter-bank formulations) finds the mesh's
    "data" axis and runs on each device's shard of the batch (`gld.hypernet`)."""

    @functools.wraps(jitted)
    def call(*args):
        with jax.set_mesh(mesh):
            return jitted(*args)

    return call


def jit_train_step(train_step: Callable, mesh: Mesh) -> Callable:
    """`train_step` compiled with replicated state, sharded batch and donated state."""
    jitted = jax.jit(
        train_step,
        in_shardings=(replicated(mesh), batch_sharded(mesh), replicated(mesh)),
        out_shardings=(replicated(mesh), replicated(mesh)),
        donate_argnums=0,
    )
    return _under_mesh(jitted, mesh)


def jit_eval_step(eval_step: Callable, mesh: Mesh) -> Callable:
    jitted = jax.jit(
        eval_step,
        in_shardings=(replicated(mesh), batch_sharded(mesh)),
        out_shardings=batch_sharded(mesh),
    )
    return _under_mesh(jitted, mesh)


def gather(tree: Any) -> Any:
    """Fully materialise a (possibly multi-process) sharded pytree as numpy on every host."""
    if jax.process_count() == 1:
        return jax.tree_util.tree_map(np.asarray, tree)
    from jax.experimental import multihost_utils

    return multihost_utils.process_allgather(tree, tiled=True)


# --------------------------------------------------------------------------- checkpoints


def checkpoint_manager(
    workdir: str | Path, *, keep: int = 2, every: int = 1
) -> ocp.CheckpointManager:
    """The run's orbax manager: items "state" (TrainState) and "data" (grain iterator)."""
    import grain

    return ocp.CheckpointManager(
        Path(workdir).absolute() / "checkpoints",
        item_handlers={
            "state": ocp.StandardCheckpointHandler(),
            "data": grain.checkpoint.CheckpointHandler(),
        },
        options=ocp.CheckpointManagerOptions(
            max_to_keep=keep, save_interval_steps=every, create=True
        ),
    )


def save_checkpoint(manager: ocp.CheckpointManager, state: TrainState, iterator) -> None:
    import grain

    step = int(jax.device_get(state.step))
    manager.save(
        step,
        args=ocp.args.Composite(
            state=ocp.args.StandardSave(state), data=grain.checkpoint.CheckpointSave(iterator)
        ),
        force=True,
    )


def restore_checkpoint(
    manager: ocp.CheckpointManager, state: TrainState, iterator=None, step: int | None = None
) -> TrainState:
    """Restores the latest (or given) step into the structure/shardings of `state`."""
    import grain

    step = manager.latest_step() if step is None else step
    abstract = jax.tree_util.tree_map(ocp.utils.to_shape_dtype_struct, state)
    items = {"state": ocp.args.StandardRestore(abstract)}
    if iterator is not None:
        items["data"] = grain.checkpoint.CheckpointRestore(iterator)
    restored = manager.restore(step, args=ocp.args.Composite(**items))
    return restored["state"]


def write_run_config(workdir: Path, config: TrainConfig) -> None:
    """Records the run's configuration; refuses a workdir made with another architecture."""
    path = workdir / "config.json"
    if path.exists():
        previous = json.loads(path.read_text())
        saved_arch = dict(previous.get("architecture", {}))
        if "model" in saved_arch:
            name = saved_arch.pop("model")
            saved_arch = {"model": name, **model_lib.complete_stored_config(name, saved_arch)}
        current_arch = json.loads(json.dumps(config.architecture()))
        differing = sorted(
            key
            for key in set(saved_arch) | set(current_arch)
            if saved_arch.get(key) != current_arch.get(key)
        )
        if differing:
            details = ", ".join(
                f"{k}: {saved_arch.get(k)!r} in the workdir vs {current_arch.get(k)!r} now"
                for k in differing
            )
            raise ValueError(
                f"workdir {workdir} holds a run of a different architecture ({details}); "
                "use another --workdir or the original flags"
            )
        for key in ("dataset", "height", "width"):
            if previous.get("config", {}).get(key) not in (None, getattr(config, key)):
                raise ValueError(
                    f"workdir {workdir} was trained on {key}={previous['config'][key]!r}, "
                    f"not {getattr(config, key)!r}"
                )
    if jax.process_index() == 0:
        stored = dataclasses.asdict(config)
        # Every architecture value is written out; the speed-only formulation only if given.
        stored["model_config"] = {
            **{k: v for k, v in config.architecture().items() if k != "model"},
            **config.model_config,
        }
        payload = {"architecture": config.architecture(), "config": stored}
        path.write_text(json.dumps(payload, indent=2, sort_keys=True) + "\n")


def load_run_config(workdir: str | Path) -> TrainConfig:
    """The TrainConfig a workdir was trained with."""
    path = Path(workdir) / "config.json"
    if not path.exists():
        raise FileNotFoundError(f"{path} not found: is {workdir} a gld training workdir?")
    values = json.loads(path.read_text())["config"]
    values["model_config"] = model_lib.complete_stored_config(
        values.get("model", "global_local"), values.get("model_config", {})
    )
    return TrainConfig(**values)


def load_trained(
    workdir: str | Path, step: int | None = None
) -> tuple[nn.Module, dict, TrainConfig]:
    """The model, its trained variables and the run's config, from a workdir."""
    workdir = Path(workdir)
    config = load_run_config(workdir)
    model = model_lib.make_model(config.model, **config.model_config)
    optimizer = config_optimizer(config)
    template = create_train_state(model, optimizer, config.height, config.width, config.seed)
    manager = checkpoint_manager(workdir)
    if manager.latest_step() is None:
        raise FileNotFoundError(f"no checkpoint in {workdir / 'checkpoints'}")
    state = restore_checkpoint(manager, template, step=step)
    manager.close()
    return model, state.variables(), config


# --------------------------------------------------------------------------- the loop


class MetricsLogger:
    """metrics.jsonl + TensorBoard, written by process 0 only."""

    def __init__(self, workdir: Path):
        self.enabled = jax.process_index() == 0
        self.path = workdir / "metrics.jsonl"
        self.writer = None
        if self.enabled:
            from tensorboardX import SummaryWriter

            self.writer = SummaryWriter(str(workdir / "tensorboard"))

    def write(self, step: int, values: dict[str, float], prefix: str = "train") -> None:
        if not self.enabled:
            return
        record = {"step": step, "split": prefix, **values}
        with self.path.open("a") as stream:
            stream.write(json.dumps(record) + "\n")
        for name, value in values.items():
            if isinstance(value, int | float) and math.isfinite(value):
                self.writer.add_scalar(f"{prefix}/{name}", value, step)
        self.writer.flush()

    def close(self) -> None:
        if self.writer is not None:
            self.writer.close()


def evaluate_source(
    model: nn.Module,
    variables: dict,
    source,
    *,
    batch_size: int,
    flow: str = "estimated",
    mesh: Mesh | None = None,
    max_examples: int = 0,
    eval_step: Callable | None = None,
    progress: bool = False,
) -> tuple[dict[str, np.ndarray], list[str]]:
    """Per-example metrics over a whole split (or its first `max_examples`).

    Returns:
      (name -> [N] values incl. "example_mask", ids [N]); padded rows have mask False.
    """
    mesh = mesh or make_mesh()
    local_batch = per_process_batch_size(batch_size, mesh)
    if max_examples:
        source = input_pipeline.first_records(source, max_examples)
    eval_step = eval_step or jit_eval_step(make_eval_step(model=model), mesh)
    variables = jax.device_put(variables, replicated(mesh))
    batches = input_pipeline.eval_batches(
        source,
        batch_size=local_batch,
        flow_source=flow,
        process_index=jax.process_index(),
        process_count=jax.process_count(),
    )
    if progress and jax.process_index() == 0:
        from tqdm import tqdm

        total = input_pipeline.num_eval_batches(len(source), local_batch, jax.process_count())
        batches = tqdm(batches, total=total, desc="evaluate", unit="batch", leave=False)
    collected: dict[str, list] = {}
    ids: list[str] = []
    for batch in batches:
        device_batch = to_global_batch(batch, mesh, EVAL_KEYS)
        result = gather(eval_step(variables, device_batch))
        for name, values in result.items():
            collected.setdefault(name, []).append(np.asarray(values))
        ids.extend(_gather_ids(batch["id"]))
    per_example = {name: np.concatenate(values) for name, values in collected.items()}
    return per_example, ids


def _gather_ids(ids: np.ndarray) -> list[str]:
    if jax.process_count() == 1:
        return [str(i) for i in ids]
    from jax.experimental import multihost_utils

    encoded = np.array([list(str(i).encode()[:120].ljust(120, b"\0")) for i in ids], np.uint8)
    gathered = multihost_utils.process_allgather(encoded, tiled=True)
    return [bytes(row).rstrip(b"\0").decode() for row in np.asarray(gathered)]


def train_and_evaluate(
    config: TrainConfig,
    workdir: str | Path,
    train_source,
    test_source=None,
    *,
    progress: bool = True,
    print_fn: Callable[[str], None] = print,
) -> TrainState:
    """Trains (resuming from the workdir's last checkpoint) and evaluates periodically.

    Args:
      config: the run.
      workdir: where checkpoints, logs and evaluations go.
      train_source, test_source: random-access record sources (TFDS data sources).
      progress: show a progress bar with step rate and ETA.
      print_fn: where start-up information goes.

    Returns:
      The final TrainState.

    Raises:
      NonFiniteLossError: the loss became NaN/inf (the step is named; nothing is saved).
    """
    workdir = Path(workdir)
    workdir.mkdir(parents=True, exist_ok=True)
    write_run_config(workdir, config)
    mesh = make_mesh()
    local_batch = per_process_batch_size(config.batch_size, mesh)
    model = model_lib.make_model(config.model, **config.model_config)
    optimizer = config_optimizer(config)
    state = create_train_state(model, optimizer, config.height, config.width, config.seed)
    if jax.process_index() == 0:
        for name, count in model_lib.parameter_counts(state.params).items():
            print_fn(f"parameters {name}: {count:,}")

    dataset = input_pipeline.train_dataset(
        train_source,
        batch_size=local_batch,
        seed=config.seed,
        gt_pixels=config.gt_pixels,
        flow_source=config.flow,
        augment=config.augment,
        fixed_sparse_pixels=config.fixed_sparse_pixels,
        worker_count=config.worker_count,
        process_index=jax.process_index(),
        process_count=jax.process_count(),
    )
    iterator = iter(dataset)
    manager = checkpoint_manager(workdir, keep=config.keep_checkpoints)
    if manager.latest_step() is not None:
        state = restore_checkpoint(manager, state, iterator)
        print_fn(f"resumed from step {int(state.step)} in {workdir / 'checkpoints'}")
    state = jax.device_put(state, replicated(mesh))
    train_step = jit_train_step(
        make_train_step(model=model, optimizer=optimizer, loss_weights=config.loss_weights()),
        mesh,
    )
    eval_step = jit_eval_step(make_eval_step(model=model), mesh)
    logger = MetricsLogger(workdir)
    base_rng = jax.random.wrap_key_data(jnp.asarray(jax.device_get(state.rng)))

    start_step = int(jax.device_get(state.step))
    bar = None
    if progress and jax.process_index() == 0:
        from tqdm import tqdm

        bar = tqdm(
            total=config.steps, initial=start_step, desc="train", unit="step", dynamic_ncols=True
        )
    window_start, window_steps = time.perf_counter(), 0
    pending: tuple[int, dict] | None = None
    try:
        for step in range(start_step, config.steps):
            batch = to_global_batch(next(iterator), mesh, TRAIN_KEYS)
            state, step_metrics = train_step(state, batch, jax.random.fold_in(base_rng, step))
            # Check the previous step's loss while this one runs (keeps dispatch async).
            if pending is not None:
                _check_finite(*pending)
            pending = (step + 1, step_metrics)
            window_steps += 1
            done = step + 1
            if bar is not None:
                bar.update(1)
            if done % config.log_every == 0 or done == config.steps:
                _check_finite(*pending)
                values = {k: float(v) for k, v in jax.device_get(step_metrics).items()}
                elapsed = time.perf_counter() - window_start
                values["steps_per_sec"] = window_steps / max(elapsed, 1e-9)
                values["examples_per_sec"] = values["steps_per_sec"] * config.batch_size
                logger.write(done, values)
                if bar is not None:
                    bar.set_postfix(loss=f"{values['loss']:.4f}")
                window_start, window_steps = time.perf_counter(), 0
            if done % config.checkpoint_every == 0 or done == config.steps:
                _check_finite(*pending)
                save_checkpoint(manager, state, iterator)
            if (
                test_source is not None
                and config.eval_every
                and (done % config.eval_every == 0 or done == config.steps)
            ):
                per_example, _ = evaluate_source(
                    model,
                    state.variables(),
                    test_source,
                    batch_size=config.eval_batch_size,
                    flow=config.flow,
                    mesh=mesh,
                    max_examples=config.eval_examples,
                    eval_step=eval_step,
                )
                summary = metrics.summarise(per_example, per_example.pop("example_mask"))
                logger.write(
                    done,
                    {k: v["mean"] for k, v in summary.items() if k in metrics.DEPTH_METRICS},
                    prefix="test",
                )
                if bar is not None:
                    bar.write(
                        f"step {done}: test "
                        + ", ".join(
                            f"{metrics.METRIC_NAMES[k]} {summary[k]['mean']:.4f}"
                            for k in metrics.DEPTH_METRICS
                        )
                    )
        if pending is not None:
            _check_finite(*pending)
    finally:
        if bar is not None:
            bar.close()
        manager.wait_until_finished()
        manager.close()
        logger.close()
    return state


def _check_finite(step: int, step_metrics: dict) -> None:
    loss = float(jax.device_get(step_metrics["loss"]))
    if not math.isfinite(loss):
        raise NonFiniteLossError(
            f"loss is {loss} at step {step}; stopping. The last good checkpoint is kept; "
            "lower --learning_rate or check the data for NaN/inf"
        )
