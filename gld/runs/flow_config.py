"""A flow-network training run's options (`FlowTrainConfig`), and its optimiser.

    config = FlowTrainConfig(steps=5000, learning_rate=1e-3).validate()

Fields with help are the flags of `experiments.train_flow` (`gld.runs.options`);
`model_config` holds `FlowNet`'s arguments. A flow run's workdir stores the config in
`flow_config.json` (`FLOW_CONFIG_FILE`, written by `gld.training.flow_trainer`).
"""

from __future__ import annotations

import dataclasses
import json
from typing import Any

import optax

from gld.models.flow_net import FlowNet, check_architecture
from gld.runs.options import LR_SCHEDULES, LoopOptions, check_option, check_schedule, option
from gld.runs.state import make_optimizer

FLOW_CONFIG_FILE = "flow_config.json"
LOSSES = ("epe", "robust")


@dataclasses.dataclass
class FlowTrainConfig(LoopOptions):
    """A flow-network training run, as plain values. Fields with help are flags of
    `experiments.train_flow`; `model_config` holds `FlowNet`'s arguments."""

    model_config: dict[str, Any] = dataclasses.field(default_factory=dict)
    batch_size: int = option(8, "Global batch size, over all processes and devices.", at_least=1)
    steps: int = option(5000, "Training steps.", at_least=1)
    learning_rate: float = option(1e-3, "Adam (peak) learning rate.", above=0)
    lr_schedule: str = option(
        "cosine", "constant or cosine (warm-up, then decay to 1%).", LR_SCHEDULES
    )
    warmup_steps: int = option(100, "Linear warm-up steps of the cosine schedule.", at_least=0)
    loss: str = option(
        "epe", "epe (mean end-point error) or robust (PWC-Net's (|du|+|dv|+0.01)^0.4).", LOSSES
    )
    pyramid_weight: float = option(
        0.5, "Weight of the mean per-level loss next to the full-resolution one.", at_least=0
    )
    augment: bool = option(True, "Rotate-180 / mirror-x augmentation.")
    seed: int = option(0, "Seed of initialisation, data order and augmentation.", at_least=0)
    checkpoint_every: int = option(500, "Steps between checkpoints.", at_least=1)

    def architecture(self) -> dict[str, Any]:
        """Every `FlowNet` argument, defaults filled in, as JSON values."""
        defaults = {
            field.name: field.default
            for field in dataclasses.fields(FlowNet)
            if field.name not in ("parent", "name")
        }
        unknown = sorted(set(self.model_config) - set(defaults))
        if unknown:
            raise ValueError(f"model_config has unknown FlowNet options {unknown}")
        return json.loads(json.dumps({**defaults, **self.model_config}))

    def make_model(self) -> FlowNet:
        architecture = self.architecture()
        return FlowNet(
            **{k: tuple(v) if isinstance(v, list) else v for k, v in architecture.items()}
        )

    def validate(self) -> FlowTrainConfig:
        """Raises ValueError naming the first option out of range; returns self."""
        for field in flag_fields():
            check_option(field, getattr(self, field.name))
        check_schedule(self.lr_schedule, self.warmup_steps, self.steps)
        check_architecture(**self.architecture())
        levels = len(self.architecture()["feature_channels"])
        if self.height and self.width and (self.height % 2**levels or self.width % 2**levels):
            raise ValueError(
                f"feature_channels: {levels} pyramid levels need the images' size to be "
                f"divisible by {2**levels}; {self.dataset or 'the dataset'} is "
                f"{self.width}x{self.height}"
            )
        return self


def flag_fields() -> list[dataclasses.Field]:
    """The FlowTrainConfig fields that are command-line options."""
    return [field for field in dataclasses.fields(FlowTrainConfig) if "help" in field.metadata]


# ------------------------------------------------------------------------------- loss


def make_flow_optimizer(config: FlowTrainConfig) -> optax.GradientTransformation:
    """The optimiser of a flow run."""
    return make_optimizer(
        config.learning_rate,
        config.lr_schedule,
        steps=config.steps,
        warmup_steps=config.warmup_steps,
    )
