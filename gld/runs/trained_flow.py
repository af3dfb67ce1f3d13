"""A trained flow network, loaded from its run without the trainer.

    network = TrainedFlowNet("runs/flow")          # newest intact checkpoint
    flow = network(image1, image2)                 # [H, W, 2] float32 pixels

`load_flow_run` restores a flow run's model, variables, config and step;
`TrainedFlowNet` wraps it as a numpy flow estimator (the "flow_net:<workdir>" estimator
of `gld.flow`); `load_pretrained_flow` starts a depth model's flow network from one.
"""

from __future__ import annotations

import functools
import hashlib
import json
from pathlib import Path
from typing import Any

import jax
import numpy as np

from gld import flow as flow_lib
from gld.arguments import MissingInputError
from gld.flow import FLOW_CONFIG_FILE
from gld.images import as_unit_rgb
from gld.models.flow_depth import check_flow_net_workdir
from gld.models.flow_net import FlowNet
from gld.runs import checkpoints as checkpoint_lib
from gld.runs import state as state_lib
from gld.runs.flow_config import FlowTrainConfig


def load_flow_run(
    workdir: str | Path, step: int | None = None
) -> tuple[FlowNet, dict, FlowTrainConfig, int]:
    """(model, trained variables, config, step) of a flow workdir: its newest intact
    checkpoint, or exactly `step`."""
    workdir = Path(workdir)
    path = workdir / FLOW_CONFIG_FILE
    if not path.exists():
        raise MissingInputError(f"{path} not found: {workdir} holds no flow-network run")
    stored = json.loads(path.read_text())
    config = FlowTrainConfig(**stored["config"])
    model = config.make_model()
    # Shapes and dtypes are all a restore needs: the real initial state would compile
    # every initialiser (seconds) only to be overwritten.
    template = jax.eval_shape(
        lambda: state_lib.create_flow_state(
            model, config.optimizer(), config.height, config.width, config.seed
        )
    )
    manager = checkpoint_lib.checkpoint_manager(workdir)
    try:
        restored = checkpoint_lib.restore_intact_checkpoint(manager, template, step=step)
    finally:
        manager.close()
    return model, restored.state.variables(), config, restored.step


def params_digest(params) -> str:
    """SHA-256 of a parameter tree's values (in the tree's order): names a checkpoint's
    weights in a dataset card or a depth run's log."""
    digest = hashlib.sha256()
    for leaf in jax.tree.leaves(params):
        digest.update(np.ascontiguousarray(np.asarray(leaf, np.float32)).tobytes())
    return digest.hexdigest()


class TrainedFlowNet:
    """A trained flow network as a numpy estimator, `(image1, image2) -> [H, W, 2]`
    float32 pixels (the signature of `gld.flow.ESTIMATORS`; images uint8 or float, see
    `gld.images.as_unit_rgb`). One compiled forward pass per image size."""

    def __init__(self, workdir: str | Path, step: int | None = None):
        self.workdir = Path(workdir)
        self.model, self.variables, self.config, self.step = load_flow_run(workdir, step)
        self._forward = jax.jit(
            lambda variables, image1, image2: self.model.apply(variables, image1, image2)["flow"]
        )

    def describe(self) -> dict[str, Any]:
        """The network's workdir, checkpoint step, architecture and parameter digest."""
        return {
            "workdir": str(self.workdir.resolve()),
            "step": int(self.step),
            "architecture": self.config.architecture(),
            "params_sha256": params_digest(self.variables["params"]),
        }

    def __call__(self, image1: np.ndarray, image2: np.ndarray) -> np.ndarray:
        first = as_unit_rgb(image1, "image1")
        second = as_unit_rgb(image2, "image2")
        if first.shape != second.shape:
            raise ValueError(
                f"image1 and image2 must have the same size, got {first.shape} and {second.shape}"
            )
        flow = self._forward(self.variables, first[None], second[None])
        return np.asarray(flow[0], np.float32)


def load_pretrained_flow(params: dict[str, Any], flow_net_workdir: str) -> tuple[dict, str] | None:
    """`params` with its "flow_net" subtree replaced by the run's trained parameters,
    and a line saying so; None when `flow_net_workdir` is empty.

    Raises:
      ValueError: the run's network has another architecture than the model's.
    """

    if not flow_net_workdir:
        return None
    check_flow_net_workdir(flow_net_workdir)
    network = TrainedFlowNet(Path(flow_net_workdir).expanduser())
    trained = network.variables["params"]
    expected = jax.tree.map(lambda leaf: leaf.shape, params["flow_net"])
    found = jax.tree.map(lambda leaf: leaf.shape, trained)
    if expected != found:
        raise ValueError(
            f"the flow network of {flow_net_workdir} has another architecture "
            f"({network.config.architecture()}) than the depth model's FlowNet (its "
            "defaults): train one with the default architecture"
        )
    note = (
        f"flow network initialised from {flow_net_workdir} (step {network.step}, "
        f"parameters sha256 {params_digest(trained)[:12]})"
    )
    return {**params, "flow_net": trained}, note


@functools.lru_cache(maxsize=4)
def _trained_network(workdir: str) -> TrainedFlowNet:
    return TrainedFlowNet(workdir)


def _network_of(method: str) -> TrainedFlowNet:
    return _trained_network(
        str(Path(method[len(flow_lib.LEARNED_PREFIX) :]).expanduser().resolve())
    )


def estimate_flow(
    image1: np.ndarray, image2: np.ndarray, method: str = flow_lib.DEFAULT_ESTIMATOR
) -> np.ndarray:
    """Flow I1 -> I2 [H, W, 2] float32 by any estimator name: a classical one of
    `gld.flow.ESTIMATORS`, or "flow_net:<workdir>" of a trained network (loaded once)."""
    flow_lib.check_estimator(method)
    if flow_lib.is_learned(method):
        return _network_of(method)(image1, image2)
    return flow_lib.estimate(image1, image2, method)


def describe_flow(method: str) -> dict[str, Any]:
    """What produced a stored flow, for a dataset's card: {"estimator": method}, plus the
    workdir, checkpoint step and parameter digest of a trained network."""
    flow_lib.check_estimator(method)
    if not flow_lib.is_learned(method):
        return flow_lib.describe(method)
    return {"estimator": method, **_network_of(method).describe()}
