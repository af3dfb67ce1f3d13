"""An online run's checkpoints: the learner's whole state at a stream position, with orbax.

    <workdir>/checkpoints/<position>/   state (model, optimiser: TrainState),
                                        buffer (the replay buffer's arrays),
                                        meta (counters, the buffer's generator, settings)

The step of a checkpoint is the stream position it resumes from (the next frame to
observe). Orbax writes a step whole or not at all, so a run killed while saving resumes
from the one before; two are kept.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import jax
import numpy as np
import orbax.checkpoint as ocp

from gld.online.learner import OnlineLearner
from gld.runs.checkpoints import save_arrays_from_one_replica

CHECKPOINTS_DIR = "checkpoints"


def manager(workdir: str | Path) -> ocp.CheckpointManager:
    """The run's orbax manager (items state, buffer, meta; the newest two kept; arrays
    written from one replica, `gld.runs.checkpoints.save_arrays_from_one_replica`)."""
    save_arrays_from_one_replica()
    return ocp.CheckpointManager(
        Path(workdir).absolute() / CHECKPOINTS_DIR,
        item_handlers={
            "state": ocp.StandardCheckpointHandler(),
            "buffer": ocp.StandardCheckpointHandler(),
            "meta": ocp.JsonCheckpointHandler(),
        },
        options=ocp.CheckpointManagerOptions(max_to_keep=2, create=True),
    )


def save(checkpoints: ocp.CheckpointManager, learner: OnlineLearner, meta: dict[str, Any]) -> int:
    """Saves the learner at its position (waiting until written); the position."""
    state = learner.state()
    position = int(state["counters"]["next_frame"])
    buffer = state["buffer"]
    checkpoints.save(
        position,
        args=ocp.args.Composite(
            state=ocp.args.StandardSave(state["train_state"]),
            buffer=ocp.args.StandardSave(buffer["arrays"]),
            meta=ocp.args.JsonSave(
                {
                    **meta,
                    "counters": state["counters"],
                    "buffer_settings": buffer["settings"],
                    "buffer_generator": buffer["generator"],
                }
            ),
        ),
        force=True,
    )
    checkpoints.wait_until_finished()
    return position


def saved_meta(checkpoints: ocp.CheckpointManager) -> dict[str, Any] | None:
    """The newest checkpoint's meta (what the run was), or None without one."""
    position = checkpoints.latest_step()
    if position is None:
        return None
    restored = checkpoints.restore(position, args=ocp.args.Composite(meta=ocp.args.JsonRestore()))
    return restored["meta"]


def restore(checkpoints: ocp.CheckpointManager, learner: OnlineLearner) -> dict[str, Any] | None:
    """Restores the newest checkpoint into `learner`; its meta, or None without one."""
    position = checkpoints.latest_step()
    if position is None:
        return None
    current = learner.state()
    abstract = jax.tree.map(ocp.utils.to_shape_dtype_struct, current["train_state"])
    buffer_template = jax.tree.map(
        lambda array: np.zeros(array.shape, array.dtype), current["buffer"]["arrays"]
    )
    restored = checkpoints.restore(
        position,
        args=ocp.args.Composite(
            state=ocp.args.StandardRestore(abstract),
            buffer=ocp.args.StandardRestore(buffer_template),
            meta=ocp.args.JsonRestore(),
        ),
    )
    meta = restored["meta"]
    learner.restore(
        {
            "train_state": restored["state"],
            "buffer": {
                "arrays": {key: np.asarray(value) for key, value in restored["buffer"].items()},
                "settings": meta["buffer_settings"],
                "generator": meta["buffer_generator"],
            },
            "counters": meta["counters"],
        }
    )
    return meta
