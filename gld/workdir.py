"""A run's directory: checkpoints, the stored configuration, and the metrics log.

    <workdir>/checkpoints/   orbax: the TrainState ("state") and the grain iterator ("data")
    <workdir>/config.json    the TrainConfig and the architecture (a workdir refuses another)
    <workdir>/metrics.jsonl  one JSON line per logged step (and per evaluation)
    <workdir>/tensorboard/   the same scalars for TensorBoard

`load_trained` gives back the model, its trained variables and the run's config.
"""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path

import flax.linen as nn
import jax
import orbax.checkpoint as ocp

from gld import config as config_lib
from gld import model as model_lib
from gld import state as state_lib
from gld.state import TrainState


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


def write_run_config(workdir: Path, config: config_lib.TrainConfig) -> None:
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


def load_run_config(workdir: str | Path) -> config_lib.TrainConfig:
    """The TrainConfig a workdir was trained with."""
    path = Path(workdir) / "config.json"
    if not path.exists():
        raise FileNotFoundError(f"{path} not found: is {workdir} a gld training workdir?")
    return config_lib.from_stored(json.loads(path.read_text())["config"])


def load_trained(
    workdir: str | Path, step: int | None = None
) -> tuple[nn.Module, dict, config_lib.TrainConfig]:
    """The model, its trained variables and the run's config, from a workdir."""
    workdir = Path(workdir)
    config = load_run_config(workdir)
    model = model_lib.make_model(config.model, **config.model_config)
    optimizer = state_lib.config_optimizer(config)
    template = state_lib.create_train_state(
        model, optimizer, config.height, config.width, config.seed
    )
    manager = checkpoint_manager(workdir)
    if manager.latest_step() is None:
        raise FileNotFoundError(f"no checkpoint in {workdir / 'checkpoints'}")
    state = restore_checkpoint(manager, template, step=step)
    manager.close()
    return model, state.variables(), config


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
