"""A training run's configuration: one definition of every option, with its help text.

`TrainConfig` is the single source: the launchers derive their command-line flags from
its fields (`experiments.common.define_option_flags`), and a workdir's `config.json` stores it
(`gld.runs.workdir`). A field's metadata holds the flag's help, choices and bounds;
fields without help (the model's constructor arguments, the dataset and its resolution)
are set by the launcher, not by a flag. The loop's and the optimiser's options are
shared with the flow trainer (`gld.runs.trainer_options`). Defaults are the paper's; the
main job's recipe is `gld.runs.recipe`.
"""

from __future__ import annotations

import dataclasses
from typing import Any

from gld.contract import FLOW_SOURCES
from gld.losses import photometric
from gld.losses import supervised as losses
from gld.models import registry
from gld.options import option
from gld.runs.trainer_options import TrainerOptions


@dataclasses.dataclass
class TrainConfig(TrainerOptions):
    """A training run, as plain values."""

    model: str = option("global_local", "Learned model.", tuple(registry.MODELS))
    model_config: dict[str, Any] = dataclasses.field(default_factory=dict)
    depth_weight: float = option(5.0, "Weight of the sparse L1 inverse-depth loss.", at_least=0)
    smoothness_weight: float = option(2.0, "Weight of the edge-aware smoothness loss.", at_least=0)
    epipolar_weight: float = option(
        0.0,
        "Weight of the epipolar loss on the pose the global parameters stand for (not the "
        "paper's; 0 = off).",
        at_least=0,
    )
    pose_teacher_weight: float = option(
        0.0,
        "Weight of the loss pulling the global parameters to the essential matrix's pose "
        "from the input flow (a classical teacher; not the paper's; 0 = off).",
        at_least=0,
    )
    photometric_smoothness_weight: float = option(
        1e-3, "Smoothness weight of the self-supervised loss (struct2depth models).", at_least=0
    )
    gt_pixels: int = option(1, "Supervised pixels per image (1, 4, 16, 64); 0 = dense.", at_least=0)
    fixed_sparse_pixels: bool = option(False, "Keep the same supervised pixels every epoch.")
    flow_source: str = option("estimated", "Which flow the model is given.", FLOW_SOURCES)

    def validate(self) -> TrainConfig:
        """Raises ValueError naming the first option whose value cannot give a sound run
        (a bound, a choice, the architecture, the schedule); returns the config."""
        self.check()
        registry.check_config(self.model, self.model_config)
        for name in ("epipolar_weight", "pose_teacher_weight"):
            if getattr(self, name) > 0 and not infers_pose(self.model, self.model_config):
                raise ValueError(
                    f"{name} needs global parameters that the model infers and that stand "
                    "for a pose: global_local with its global module, global_source encoder "
                    "and global_dim 6"
                )
        return self

    def architecture(self) -> dict[str, Any]:
        """What a checkpoint's parameters depend on (a workdir refuses other values)."""
        speed_only = {"filter_formulation"}  # changes how, not what, the model computes
        full = registry.full_config(self.model, self.model_config)
        config = {k: v for k, v in full.items() if k not in speed_only}
        return {"model": self.model, **dict(sorted(config.items()))}

    def loss_weights(self) -> losses.LossWeights | photometric.SelfSupervisedWeights:
        """The weights of the model's training loss (self-supervised or sparse)."""
        if getattr(registry.MODELS.get(self.model), "LOSS", "supervised") == "self_supervised":
            return photometric.SelfSupervisedWeights(smoothness=self.photometric_smoothness_weight)
        return losses.LossWeights(
            depth=self.depth_weight,
            smoothness=self.smoothness_weight,
            epipolar=self.epipolar_weight,
            pose_teacher=self.pose_teacher_weight,
        )


def infers_pose(model: str, model_config: dict[str, Any]) -> bool:
    """Whether a model's global parameters are inferred from its inputs and can stand for
    the camera motion (`gld.models.registry.encoder_pose`): the epipolar term applies."""
    return model == "global_local" and registry.encoder_pose(
        registry.full_config(model, model_config)
    )


def refines_pose(model: str, model_config: dict[str, Any]) -> bool:
    """Whether a model could refine its encoder's pose on its flow
    (`pose_refinement_steps`; `gld.models.registry.reads_encoder_pose`)."""
    return model == "global_local" and registry.reads_encoder_pose(
        registry.full_config(model, model_config)
    )


def reads_pose(model: str, model_config: dict[str, Any]) -> bool:
    """Whether a model could read a pose g (its encoder's or a given one) against its
    flow: subtract its rotation's flow (`derotate_flow`) and triangulate the flow under it
    (`parallax_depth`) (`gld.models.registry.reads_pose`)."""
    return model == "global_local" and registry.reads_pose(
        registry.full_config(model, model_config)
    )


# Stored config keys renamed since the first workdirs were written: old name -> new.
RENAMED_FIELDS = {"flow": "flow_source"}


def from_stored(values: dict[str, Any]) -> TrainConfig:
    """The TrainConfig of a stored `config.json` "config" entry, written by any version:
    renamed fields take their new names and model options added later take the values
    the run was trained with (`gld.models.registry.FIELDS_ADDED_LATER`)."""
    values = {RENAMED_FIELDS.get(key, key): value for key, value in values.items()}
    values["model_config"] = registry.complete_stored_config(
        values.get("model", "global_local"), values.get("model_config", {})
    )
    return TrainConfig(**values)
