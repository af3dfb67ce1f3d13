"""The depth trainer: the pure train step of a depth model, and its run in the trainers'
skeleton.

`make_train_step` builds a pure `train_step(state, batch, rng) -> (state, metrics)` with
the model's loss (sparse supervised, or self-supervised); `DepthRun` is what a depth run
adds to the skeleton every trainer runs (`gld.training.loop`: over a mesh of all devices,
resuming from and saving to the run's workdir, evaluating periodically), and
`train_and_evaluate` runs it. The same code runs on one CPU, on fake CPU devices, on a
GPU and on several processes after `jax.distributed.initialize`.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import flax.linen as nn
import jax
import jax.numpy as jnp
import optax
from jax.sharding import Mesh

from gld.evaluation import evaluate as evaluation
from gld.evaluation import metrics
from gld.flow_pose import FLOW_POSE_KEYS
from gld.losses import photometric
from gld.losses import supervised as losses
from gld.models import layers, registry
from gld.runs import checkpoints as checkpoint_lib
from gld.runs import trained_flow
from gld.runs import workdir as workdir_lib
from gld.runs.config import TrainConfig
from gld.runs.state import TrainState, create_train_state
from gld.training import loop

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


def _with_pretrained(
    model: nn.Module, state: TrainState, workdir: Path, print_fn: Callable[[str], None]
) -> TrainState:
    """A new run of a model with a pretrained flow network (`gld.models.flow_depth`'s
    `flow_net_workdir`) starts from it; a run with checkpoints restores its own (the
    pretrained run need not exist any more)."""
    flow_net_workdir = getattr(model, "flow_net_workdir", "")
    if not flow_net_workdir or checkpoint_lib.last_checkpointed_step(workdir):
        return state
    loaded = trained_flow.load_pretrained_flow(state.params, flow_net_workdir)
    if loaded is None:
        return state
    params, note = loaded
    if jax.process_index() == 0:
        print_fn(note)
    return state.replace(params=params)


class DepthRun(loop.TrainingRun):
    """A depth model's run in the trainers' skeleton (`gld.training.loop`)."""

    config: TrainConfig

    def __init__(self, config: TrainConfig, records: Mapping[str, str] | None = None):
        """`records`: extra text files for the workdir, name -> content, written with
        config.json (checked here, before anything is written)."""
        super().__init__(config)
        self.records = workdir_lib.check_records(records)

    def make_model(self) -> nn.Module:
        return registry.make_model(self.config.model, **self.config.model_config)

    def check_workdir(self, workdir: Path) -> dict[str, tuple] | None:
        return workdir_lib.check_run_config(workdir, self.config)

    def fresh_state(
        self,
        model: nn.Module,
        optimizer: optax.GradientTransformation,
        workdir: Path,
        print_fn: Callable[[str], None],
    ) -> TrainState:
        config = self.config
        state = create_train_state(model, optimizer, config.height, config.width, config.seed)
        return _with_pretrained(model, state, workdir, print_fn)

    def parameter_counts(self, state: TrainState) -> dict[str, int]:
        return registry.parameter_counts(state.params)

    def batch_keys(self, model: nn.Module) -> tuple[str, ...]:
        return batch_keys(model, self.config.loss_weights())

    def data_options(self) -> dict[str, Any]:
        config = self.config
        return {
            "gt_pixels": config.gt_pixels,
            "flow_source": config.flow_source,
            "fixed_sparse_pixels": config.fixed_sparse_pixels,
        }

    def train_step(self, model: nn.Module, optimizer: optax.GradientTransformation) -> Callable:
        return make_train_step(
            model=model, optimizer=optimizer, loss_weights=self.config.loss_weights()
        )

    def evaluation(self, model: nn.Module, mesh: Mesh, test_source) -> loop.Evaluation:
        config = self.config
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
            values = {k: v["mean"] for k, v in summary.items() if k in metrics.DEPTH_METRICS}
            return values, message

        return evaluate

    def begin(
        self,
        workdir: Path,
        start_step: int,
        changes: dict[str, tuple] | None,
        print_fn: Callable[[str], None],
    ) -> Callable[[], None]:
        """`config.json` and the launcher's records: on a new workdir now; on an existing
        one with the first checkpoint of this launch, so that they never describe steps
        not trained."""
        config, records = self.config, self.records
        records_pending = False
        if changes is None:
            workdir_lib.write_run_config(workdir, config, step=start_step, records=records)
        else:
            if changes and jax.process_index() == 0:
                when = (
                    "stored in config.json with this launch's first checkpoint"
                    if start_step < config.steps
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

        return after_checkpoint


def train_and_evaluate(
    config: TrainConfig,
    workdir: str | Path,
    train_source,
    test_source=None,
    *,
    progress: bool = True,
    print_fn: Callable[[str], None] = print,
    records: Mapping[str, str] | None = None,
    keep_compiled: bool = False,
) -> TrainState:
    """Trains a depth model (resuming from the workdir's newest intact checkpoint) and
    evaluates it periodically (`gld.training.loop.train`).

    The options, the model and optimiser and the workdir's stored config are checked
    before anything is written; the workdir is then locked before the costly start-up
    (the state, the data, compiling), and the checkpoints are checked before a step.
    Then `config.json` and `records` are written atomically: on a new workdir before the
    first step, on an existing one with the first checkpoint this launch saves, if
    anything differs (the rule, and config.json's "history" of changed options, are in
    `gld.runs.workdir`). The changed options are printed at every launch.

    Args:
      config: the run.
      workdir: where checkpoints, logs and evaluations go.
      train_source, test_source: random-access record sources (TFDS data sources).
      progress: show a progress bar with step rate and ETA.
      print_fn: where start-up information and checkpoint warnings go.
      records: extra text files for the workdir, name -> content (e.g. the launcher's
        {"flags.txt": ...}), written with config.json.
      keep_compiled: keep the compiled programs in `<workdir>/compile_cache` from the
        start-up on, for the rest of the process (`gld.runs.workdir.keep_compiled_programs`).

    Returns:
      The final TrainState.

    Raises:
      ValueError: a bad option or record name, or a workdir holding another architecture
        or dataset (nothing is written).
      WorkdirLockedError: another process is training in the workdir (it is named).
      CorruptCheckpointError: the workdir has checkpoints but none is intact.
      NonFiniteLossError: the loss became NaN/inf (the step is named; nothing is saved).
      gld.files.DiskFullError: the workdir's disk is full (the checkpoints saved before
        are kept).
    """
    return loop.train(
        DepthRun(config, records),
        workdir,
        train_source,
        test_source,
        progress=progress,
        print_fn=print_fn,
        keep_compiled=keep_compiled,
    )
