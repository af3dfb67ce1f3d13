"""Depth models that estimate their own flow with the learned flow network (`FlowNet`).

The paper's flow experiment (its Table "Fine-tuning Optical Flow") compares three ways
of using a learned flow estimator:

- `GlobalLocalFlowNet` with `flow_trainable=False`: the global-local model on the
  network's flow, the network fixed ("Ours (no finetune)");
- the same with `flow_trainable=True`: the flow network fine-tuned end to end with the
  sparse depth loss ("Ours (finetune PWC)");
- `FlowNetHead`: the flow network followed by a small conv head of (32, 16, 1) 3x3
  filters, stride 1, everything trained with the sparse depth loss only ("PWC (*)").

Both take the depth models' call signature, `model(image1, image2, flow, *, train)`,
and ignore the given (stored) `flow`: they compute theirs from the images, and return
it as "flow" next to the depth, so that what fine-tuning does to the flow can be
measured. The flow network starts from a trained run of `experiments.train_flow` when
`flow_net_workdir` names one (its newest intact checkpoint, loaded by
`gld.runs.trained_flow.load_pretrained_flow` when a training run starts; a resumed run
restores its own
checkpoint instead), from a random initialisation otherwise. Its architecture is
FlowNet's default, which a pretrained run must match.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence

import flax.linen as nn
import jax

from gld import flow as flow_lib
from gld.models import layers
from gld.models.flow_net import FlowNet
from gld.models.global_local import GlobalLocal

HEAD_CHANNELS = (32, 16, 1)
# The head sees the flow in tenths of the image size, as the global-local model
# (its `flow_scale` default).
HEAD_FLOW_SCALE = layers.FLOW_SCALE


def check_flow_net_workdir(flow_net_workdir: str) -> None:
    """Raises ValueError unless `flow_net_workdir` is empty or a flow network's run."""

    if flow_net_workdir:
        flow_lib.check_estimator(flow_lib.LEARNED_PREFIX + flow_net_workdir)


class _OnFlowNet(nn.Module):
    """What both models share: the flow network, its pretrained start, its flow."""

    flow_net_workdir: str = ""

    def estimate_flow(self, image1: jax.Array, image2: jax.Array, flow: jax.Array) -> jax.Array:
        """The network's flow [B, H, W, 2] (inside the caller's compact `__call__`); the
        given `flow` is only checked for its shape."""
        layers.check_inputs(image1, image2, flow)
        return FlowNet(name="flow_net")(image1, image2)["flow"]


class GlobalLocalFlowNet(_OnFlowNet):
    """The global-local model on `FlowNet`'s flow.

    Attributes:
      flow_net_workdir: a flow network's run to start from ("" = random).
      flow_trainable: fine-tune the flow network with the depth loss (False: its
        parameters get no gradient and stay as initialised).
      global_local: options of the global-local model (`gld.models.global_local.GlobalLocal`'s
        arguments; empty: its defaults).
    """

    flow_trainable: bool = False
    global_local: Mapping = dataclasses.field(default_factory=dict)

    @nn.compact
    def __call__(
        self, image1: jax.Array, image2: jax.Array, flow: jax.Array, *, train: bool = False
    ) -> dict[str, jax.Array]:
        """{'inv_depth', 'depth' [B, H, W], 'flow' [B, H, W, 2] (the network's), and the
        global-local outputs}; the given `flow` only fixes the expected shape."""
        estimated = self.estimate_flow(image1, image2, flow)
        if not self.flow_trainable:
            estimated = jax.lax.stop_gradient(estimated)
        options = {k: tuple(v) if isinstance(v, list) else v for k, v in self.global_local.items()}
        outputs = GlobalLocal(**options, name="global_local")(
            image1, image2, estimated, train=train
        )
        return {**outputs, "flow": estimated}


class FlowNetHead(_OnFlowNet):
    """`FlowNet` followed by a conv head turning its flow into inverse depth, trained
    together with the depth loss (the paper's "PWC (*)" row).

    The head sees the flow in tenths of the image size (`HEAD_FLOW_SCALE`); LeakyReLU
    between its convolutions.

    Attributes:
      flow_net_workdir: a flow network's run to start from ("" = random).
      head_channels: the head's 3x3 convolutions, stride 1 (the paper's (32, 16, 1)).
    """

    head_channels: Sequence[int] = HEAD_CHANNELS

    @nn.compact
    def __call__(
        self, image1: jax.Array, image2: jax.Array, flow: jax.Array, *, train: bool = False
    ) -> dict[str, jax.Array]:
        """{'inv_depth', 'depth' [B, H, W], 'flow' [B, H, W, 2] (the network's)}."""
        del train
        if not self.head_channels or self.head_channels[-1] != 1:
            raise ValueError(
                f"head_channels must end with 1 (inverse depth), got {tuple(self.head_channels)}"
            )
        estimated = self.estimate_flow(image1, image2, flow)
        features = layers.scaled_flow(estimated, HEAD_FLOW_SCALE)
        for index, channels in enumerate(self.head_channels):
            features = layers.Conv(channels, (3, 3), name=f"head{index}")(features)
            if index < len(self.head_channels) - 1:
                features = layers.leaky_relu(features)
        return {**layers.depth_outputs(features), "flow": estimated}
