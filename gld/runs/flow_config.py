"""A flow-network training run's options (`FlowTrainConfig`).

    config = FlowTrainConfig(steps=5000, learning_rate=1e-3).validate()

Fields with help are the flags of `experiments.train_flow` (`gld.options`); the loop's
and the optimiser's are shared with the depth trainer (`gld.runs.trainer_options`), with
this trainer's defaults. `model_config` holds `FlowNet`'s arguments. A flow run's workdir
stores the config in `flow_config.json` (`gld.flow.FLOW_CONFIG_FILE`, written by
`gld.training.flow_trainer`).
"""

from __future__ import annotations

import dataclasses
import json
from typing import Any

from gld.models.flow_net import FlowNet, check_architecture
from gld.options import option, with_default
from gld.runs.trainer_options import TrainerOptions

LOSSES = ("epe", "robust")


@dataclasses.dataclass
class FlowTrainConfig(TrainerOptions):
    """A flow-network training run, as plain values. Fields with help are flags of
    `experiments.train_flow`; `model_config` holds `FlowNet`'s arguments."""

    model_config: dict[str, Any] = dataclasses.field(default_factory=dict)
    batch_size: int = with_default(TrainerOptions, "batch_size", 8)
    steps: int = with_default(TrainerOptions, "steps", 5000)
    learning_rate: float = with_default(TrainerOptions, "learning_rate", 1e-3)
    lr_schedule: str = with_default(TrainerOptions, "lr_schedule", "cosine")
    warmup_steps: int = with_default(TrainerOptions, "warmup_steps", 100)
    checkpoint_every: int = with_default(TrainerOptions, "checkpoint_every", 500)
    loss: str = option(
        "epe", "epe (mean end-point error) or robust (PWC-Net's (|du|+|dv|+0.01)^0.4).", LOSSES
    )
    pyramid_weight: float = option(
        0.5, "Weight of the mean per-level loss next to the full-resolution one.", at_least=0
    )

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
        self.check()
        check_architecture(**self.architecture())
        levels = len(self.architecture()["feature_channels"])
        if self.height and self.width and (self.height % 2**levels or self.width % 2**levels):
            raise ValueError(
                f"feature_channels: {levels} pyramid levels need the images' size to be "
                f"divisible by {2**levels}; {self.dataset or 'the dataset'} is "
                f"{self.width}x{self.height}"
            )
        return self
