"""The options every trainer shares: the loop (length, batch, seed, logging, periodic
evaluation, checkpoints, input workers, the data) and the optimiser.

    class FlowTrainConfig(TrainerOptions):
        steps: int = with_default(TrainerOptions, "steps", 5000)

`TrainerOptions` is the base of a depth run's config (`gld.runs.config.TrainConfig`) and
a flow run's (`gld.runs.flow_config.FlowTrainConfig`); each option is written once, here,
and a trainer whose runs start elsewhere changes only the default (`gld.options.with_default`).
Defaults are the paper's depth runs'.
"""

from __future__ import annotations

import dataclasses

import optax

from gld.options import check_option, option, option_fields
from gld.runs.optimizer import OptimizerOptions, check_schedule, make_optimizer


@dataclasses.dataclass
class LoopOptions:
    """The training loop's options: its length, batch, seed and augmentation, logging,
    periodic evaluation, checkpoints, input workers, and the data's name and resolution
    (set by the launcher)."""

    batch_size: int = option(16, "Global batch size, over all processes and devices.", at_least=1)
    steps: int = option(94_000, "Training steps (the paper's: 94000 at 256x192).", at_least=1)
    augment: bool = option(True, "Rotate-180 / mirror-x augmentation.")
    seed: int = option(
        0, "Seed of initialisation, data order, augmentation and sparsity.", at_least=0
    )
    log_every: int = option(50, "Steps between metrics.jsonl / TensorBoard records.", at_least=1)
    eval_every: int = option(
        1000, "Steps between evaluations on the test split (0: off).", at_least=0
    )
    checkpoint_every: int = option(250, "Steps between checkpoints.", at_least=1)
    keep_checkpoints: int = option(2, "Checkpoints kept in the workdir.", at_least=1)
    eval_batch_size: int = option(
        16, "Batch size of the periodic and final evaluations.", at_least=1
    )
    eval_examples: int = option(
        0, "Periodic evaluation on the first N test pairs; 0 = all.", at_least=0
    )
    worker_count: int = option(0, "grain worker processes for the input pipeline.", at_least=0)
    dataset: str = ""
    height: int = 0
    width: int = 0


@dataclasses.dataclass
class TrainerOptions(LoopOptions, OptimizerOptions):
    """The loop's and the optimiser's options of a training run."""

    def check(self) -> None:
        """Raises ValueError naming the first option of the run (this class's and a
        subclass's) out of range."""
        for field in option_fields(type(self)):
            check_option(field, getattr(self, field.name))
        check_schedule(self.lr_schedule, self.warmup_steps, self.steps)
        for name in ("height", "width"):
            if getattr(self, name) < 0:
                raise ValueError(f"{name} must be positive, got {getattr(self, name)}")

    def validate(self) -> TrainerOptions:
        """`check`, for a run with no options of its own; returns self."""
        self.check()
        return self

    def optimizer(self) -> optax.GradientTransformation:
        """The run's optimiser: Adam with its schedule over the run's steps."""
        return make_optimizer(
            self.learning_rate,
            self.lr_schedule,
            steps=self.steps,
            warmup_steps=self.warmup_steps,
        )
