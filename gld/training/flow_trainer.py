"""Training the learned flow network (`gld.models.flow_net.FlowNet`) on the
records' exact flow.

The loss is the end-point error (or PWC-Net's robust fine-tuning loss) against
`gt_flow`, over `gt_flow_valid` pixels, at the output's full resolution plus, weighted
by `pyramid_weight`, at every estimated level against the truth averaged over each
level's pixel blocks (`flow_loss`). `make_flow_train_step` builds the pure step;
`FlowRun` is what a flow run adds to the skeleton every trainer runs (`gld.training.loop`:
over a mesh of all devices, resuming from and saving to a workdir with verified orbax
checkpoints of the `TrainState` and the grain iterator), and `train_flow` runs it; it
evaluates with `gld.evaluation.flow_network`.

A flow run's workdir:

    <workdir>/flow_config.json  FlowTrainConfig and the network's architecture
    <workdir>/checkpoints/      as a depth run's (gld.runs.workdir)
    <workdir>/metrics.jsonl     train and test records; tensorboard/ the same
    <workdir>/eval/flow.json, flow_table.md   the final evaluation
"""

from __future__ import annotations

import dataclasses
import json
import math
from collections.abc import Callable
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import optax
from jax.sharding import Mesh

from gld import files as files_lib
from gld.arguments import ArgumentError
from gld.evaluation import evaluate as evaluation
from gld.evaluation.flow_network import (
    NETWORK,
    STORED_FLOW,
    evaluate_flow,
    make_flow_eval_step,
)
from gld.flow import FLOW_CONFIG_FILE
from gld.models.flow_net import (
    FlowNet,
    parameter_count,
)
from gld.runs import workdir as workdir_lib
from gld.runs.flow_config import LOSSES, FlowTrainConfig
from gld.runs.state import TrainState, create_flow_state
from gld.training import loop

# Keys of a training batch the step reads (the truth; no estimated flow).
FLOW_TRAIN_KEYS = ("image1", "image2", "gt_flow", "gt_flow_valid")
# PWC-Net's robust fine-tuning loss: (|du| + |dv| + epsilon) ** q.
_ROBUST_EPSILON = 0.01
_ROBUST_EXPONENT = 0.4


def downsample_truth(
    gt_flow: jax.Array, valid: jax.Array, factor: int
) -> tuple[jax.Array, jax.Array]:
    """The truth at a pyramid level: the mean of each factor x factor block's valid flow.

    Args:
      gt_flow: [B, H, W, 2] pixels; valid: [B, H, W] bool; factor: 2**level.

    Returns:
      flow [B, H / factor, W / factor, 2] (still in input pixels) and its validity
      [B, H / factor, W / factor] (a block with at least one valid pixel).
    """
    if factor == 1:
        return gt_flow, valid
    batch, height, width, _ = gt_flow.shape
    weights = valid.astype(gt_flow.dtype).reshape(
        batch, height // factor, factor, width // factor, factor
    )
    sums = gt_flow.reshape(batch, height // factor, factor, width // factor, factor, 2)
    sums = (sums * weights[..., None]).sum(axis=(2, 4))
    counts = weights.sum(axis=(2, 4))
    return sums / jnp.maximum(counts, 1.0)[..., None], counts > 0


def pixel_losses(flow: jax.Array, gt_flow: jax.Array, loss: str = "epe") -> jax.Array:
    """Per-pixel loss [B, H, W] of flow against the truth (both [B, H, W, 2])."""
    difference = flow - gt_flow
    if loss == "epe":
        # The norm's gradient is undefined at 0; the epsilon keeps it finite.
        return jnp.sqrt(jnp.sum(difference**2, axis=-1) + 1e-12)
    if loss == "robust":
        return (jnp.sum(jnp.abs(difference), axis=-1) + _ROBUST_EPSILON) ** _ROBUST_EXPONENT
    raise ValueError(f"loss must be one of {LOSSES}, got {loss!r}")


def _masked_mean(values: jax.Array, mask: jax.Array) -> jax.Array:
    return jnp.sum(jnp.where(mask, values, 0.0)) / jnp.maximum(jnp.sum(mask), 1)


def flow_loss(
    outputs: dict[str, Any], batch: dict, *, loss: str = "epe", pyramid_weight: float = 0.5
) -> tuple[jax.Array, dict[str, jax.Array]]:
    """The multi-scale loss over valid pixels of the batch (pooled over the batch).

    Args:
      outputs: `FlowNet`'s {"flow": [B, H, W, 2], "flow_pyramid": coarsest first}.
      batch: "gt_flow" [B, H, W, 2], "gt_flow_valid" [B, H, W].
      loss: "epe" or "robust" (`pixel_losses`).
      pyramid_weight: weight of the mean of the per-level losses.

    Returns:
      (loss, terms): "loss", "full" (the full-resolution loss), "epe" (its mean
      end-point error in pixels), "level<l>" per level.
    """
    gt_flow, valid = batch["gt_flow"], batch["gt_flow_valid"]
    height = gt_flow.shape[1]
    full = _masked_mean(pixel_losses(outputs["flow"], gt_flow, loss), valid)
    terms = {"full": full}
    level_losses = []
    for level_flow in outputs["flow_pyramid"]:
        factor = height // level_flow.shape[1]
        level_truth, level_valid = downsample_truth(gt_flow, valid, factor)
        level_loss = _masked_mean(pixel_losses(level_flow, level_truth, loss), level_valid)
        terms[f"level{int(math.log2(factor))}"] = level_loss
        level_losses.append(level_loss)
    total = full
    if level_losses and pyramid_weight:
        total = total + pyramid_weight * jnp.mean(jnp.stack(level_losses))
    terms["loss"] = total
    terms["epe"] = (
        full
        if loss == "epe"
        else _masked_mean(jnp.linalg.norm(outputs["flow"] - gt_flow, axis=-1), valid)
    )
    return total, terms


# ------------------------------------------------------------------------- train step


def make_flow_train_step(
    *,
    model: FlowNet,
    optimizer: optax.GradientTransformation,
    loss: str = "epe",
    pyramid_weight: float = 0.5,
) -> Callable[[TrainState, dict, jax.Array], tuple[TrainState, dict]]:
    """Builds the pure `train_step(state, batch, rng) -> (state, metrics)`.

    The batch holds FLOW_TRAIN_KEYS; `rng` is unused (the network has no randomness) and
    kept so the step compiles like the depth trainer's (`gld.training.loop.jit_train_step`).
    """
    if loss not in LOSSES:
        raise ValueError(f"loss must be one of {LOSSES}, got {loss!r}")

    def train_step(state: TrainState, batch: dict, rng: jax.Array):
        del rng

        def loss_fn(params):
            outputs = model.apply({"params": params}, batch["image1"], batch["image2"])
            return flow_loss(outputs, batch, loss=loss, pyramid_weight=pyramid_weight)

        (_, terms), grads = jax.value_and_grad(loss_fn, has_aux=True)(state.params)
        updates, opt_state = optimizer.update(grads, state.opt_state, state.params)
        step_metrics = dict(terms)
        step_metrics["grad_norm"] = optax.global_norm(grads)
        step_metrics["learning_rate"] = jnp.asarray(
            opt_state.hyperparams["learning_rate"] if hasattr(opt_state, "hyperparams") else jnp.nan
        )
        new_state = state.replace(
            step=state.step + 1,
            params=optax.apply_updates(state.params, updates),
            opt_state=opt_state,
        )
        return new_state, step_metrics

    return train_step


# ------------------------------------------------------------------------- evaluation


# ---------------------------------------------------------------------------- workdir


def _stored(config: FlowTrainConfig) -> dict[str, Any]:
    return {
        "architecture": config.architecture(),
        "config": json.loads(json.dumps(dataclasses.asdict(config))),
    }


def check_flow_workdir(workdir: str | Path, config: FlowTrainConfig) -> dict[str, tuple]:
    """Checks `config` against the workdir, reading only; returns the options that
    differ from the stored ones ({name: (stored, now)}; empty for a new workdir).

    Raises:
      ValueError: the workdir holds a depth run, or a flow run of another architecture,
        dataset or resolution (every differing value is named).
    """
    workdir = Path(workdir)
    if (workdir / workdir_lib.CONFIG_FILE).exists():
        raise ValueError(
            f"workdir {workdir} holds a depth run ({workdir_lib.CONFIG_FILE}); use another "
            "--workdir for the flow network"
        )
    path = workdir / FLOW_CONFIG_FILE
    if not path.exists():
        return {}
    try:
        previous = json.loads(path.read_text())
    except json.JSONDecodeError as error:
        raise ValueError(f"{path} is not valid JSON ({error})") from None
    current = _stored(config)
    fixed = {f"model_config.{k}": v for k, v in current["architecture"].items()}
    stored_fixed = {f"model_config.{k}": v for k, v in previous.get("architecture", {}).items()}
    for key in ("dataset", "height", "width"):
        fixed[key] = current["config"][key]
        stored_fixed[key] = previous.get("config", {}).get(key)
    differing = sorted(
        k for k in set(fixed) | set(stored_fixed) if fixed.get(k) != stored_fixed.get(k)
    )
    if differing:
        details = ", ".join(
            f"{k}: {stored_fixed.get(k)!r} in the workdir vs {fixed.get(k)!r} now"
            for k in differing
        )
        raise ArgumentError(
            f"workdir {workdir} holds a flow run of another architecture or dataset "
            f"({details}); use another --workdir or the original flags"
        )
    stored_options = previous.get("config", {})
    return {
        key: (stored_options.get(key), value)
        for key, value in current["config"].items()
        if key != "model_config" and stored_options.get(key) != value
    }


def write_flow_config(workdir: str | Path, config: FlowTrainConfig) -> None:
    """Writes `flow_config.json` atomically (process 0)."""
    if jax.process_index() != 0:
        return
    workdir = Path(workdir)
    workdir.mkdir(parents=True, exist_ok=True)
    files_lib.write_atomically(
        workdir / FLOW_CONFIG_FILE, json.dumps(_stored(config), indent=2, sort_keys=True) + "\n"
    )


# ---------------------------------------------------------------------------- training


class FlowRun(loop.TrainingRun):
    """A flow network's run in the trainers' skeleton (`gld.training.loop`)."""

    config: FlowTrainConfig
    description = "train flow"
    postfix = "epe"

    def make_model(self) -> FlowNet:
        if not self.config.height or not self.config.width:
            raise ValueError("config.height and config.width must be the dataset's resolution")
        return self.config.make_model()

    def check_workdir(self, workdir: Path) -> dict[str, tuple]:
        return check_flow_workdir(workdir, self.config)

    def fresh_state(
        self,
        model: FlowNet,
        optimizer: optax.GradientTransformation,
        workdir: Path,
        print_fn: Callable[[str], None],
    ) -> TrainState:
        config = self.config
        return create_flow_state(model, optimizer, config.height, config.width, config.seed)

    def parameter_counts(self, state: TrainState) -> dict[str, int]:
        return {"flow_net": parameter_count(state.params)}

    def batch_keys(self, model: FlowNet) -> tuple[str, ...]:
        return FLOW_TRAIN_KEYS

    def data_options(self) -> dict[str, Any]:
        return {"gt_pixels": 0, "flow_source": "gt"}

    def train_step(self, model: FlowNet, optimizer: optax.GradientTransformation) -> Callable:
        return make_flow_train_step(
            model=model,
            optimizer=optimizer,
            loss=self.config.loss,
            pyramid_weight=self.config.pyramid_weight,
        )

    def evaluation(self, model: FlowNet, mesh: Mesh, test_source) -> loop.Evaluation:
        config = self.config
        eval_step = evaluation.jit_eval_step(make_flow_eval_step(model=model), mesh)

        def evaluate(state: TrainState) -> tuple[dict[str, float], str]:
            _, _, summary = evaluate_flow(
                model,
                state.variables(),
                test_source,
                batch_size=config.eval_batch_size,
                max_examples=config.eval_examples,
                mesh=mesh,
                eval_step=eval_step,
            )
            values = {
                "epe": summary[NETWORK]["epe"],
                "outliers": summary[NETWORK]["outliers"],
                "dis_epe": summary[STORED_FLOW]["epe"],
            }
            message = (
                f"test EPE {summary[NETWORK]['epe']:.3f} px "
                f"(DIS {summary[STORED_FLOW]['epe']:.3f} px)"
            )
            return values, message

        return evaluate

    def begin(
        self,
        workdir: Path,
        start_step: int,
        changes: dict[str, tuple] | None,
        print_fn: Callable[[str], None],
    ) -> None:
        """`flow_config.json`, with the options in force, before the first step."""
        if changes:
            print_fn(
                f"options changed since the stored config: {workdir_lib.describe_changes(changes)}"
            )
        write_flow_config(workdir, self.config)


def train_flow(
    config: FlowTrainConfig,
    workdir: str | Path,
    train_source,
    test_source=None,
    *,
    progress: bool = True,
    print_fn: Callable[[str], None] = print,
) -> TrainState:
    """Trains the flow network (resuming from the workdir's newest intact checkpoint) and
    evaluates it every `eval_every` steps on `test_source` (`gld.training.loop.train`).

    Everything is checked before anything is written: the options, the network, the
    workdir's stored config, the lock. `flow_config.json` is then written (with the
    options in force) before the first step.

    Returns:
      The final TrainState.

    Raises:
      ValueError: a bad option, or a workdir holding another run (nothing is written).
      gld.runs.lock.WorkdirLockedError: another process trains in the workdir.
      gld.runs.checkpoints.CorruptCheckpointError: no checkpoint of the workdir is intact.
      gld.training.loop.NonFiniteLossError: the loss became NaN/inf (the step is named).
      gld.files.DiskFullError: the workdir's disk is full (the checkpoints saved before
        are kept).
    """
    return loop.train(
        FlowRun(config), workdir, train_source, test_source, progress=progress, print_fn=print_fn
    )
