"""The main job's recipe, and the run policy every launch of a depth run applies.

    model_config, weights = recipe.motion_where_it_applies(model, model_config, weights, given)

The recipe is the best measured within the main job's CPU budget (WORKSPACE.md): Adam
1e-3 with 100 warm-up steps and cosine decay over 2,000 steps, and a global module that
learns the camera motion with no label: an instance-normalised encoder that sees the
flow alone, the epipolar term at 0.1, the classical pose teacher, a search of five
translation directions around the encoder's pose and fifteen Gauss-Newton steps refining
it on the flow, and a local network that sees the flow
less the flow of that pose's rotation and the inverse depth the flow gives under that
pose, and repeats the image's edge beyond it (no rim of different depth at the border).
None of it is the paper's (its recipe: Adam 1e-4, constant, the image pair and the
flow, no motion terms, zero padding). The recipe is
written here once: the train launcher's defaults, `experiments/flags/demo.flags`, the
paper suite's main-job rows and the tests all read it.

A launch applies two rules (`experiments.train`, the comparison and the paper runner):
the motion terms and the refinement are dropped where the model has no encoder's pose
to teach or refine, the derotated and triangulated flow where it has no pose as g (each
unless asked for), the search where it does not refine, and a relaunch of a workdir keeps the
architecture it was trained with for every option the command line does not give. And
the train launcher's warm-up fits any run (`warmup_that_fits`): a run too short for the
recipe's 100 steps warms up for the same 5% of its steps, unless --warmup_steps is given.
"""

from __future__ import annotations

from collections.abc import Collection
from pathlib import Path
from typing import Any

from gld.models import registry
from gld.models.global_local import ENCODER_POSE_READERS, POSE_READERS
from gld.runs import config as config_lib
from gld.runs import workdir as workdir_lib

# The global-local model's architecture in the main job (its other options: the model's
# defaults).
ARCHITECTURE = {
    "encoder_norm": "instance",
    "use_image_pair": False,
    "pose_refinement_steps": 15,
    "pose_refinement_starts": 5,
    "border": "edge",
    "derotate_flow": True,
    "parallax_depth": True,
}
# The loss weights by which the main job's global module learns the motion.
MOTION_WEIGHTS = {"epipolar_weight": 0.1, "pose_teacher_weight": 1.0}
_DEFAULTS = registry.full_config("global_local", {})
# What refines an encoder's pose on the flow (`ENCODER_POSE_READERS`), off: the model's
# defaults.
WITHOUT_AN_ENCODER_POSE = {name: _DEFAULTS[name] for name in ENCODER_POSE_READERS}
# What reads a pose against the flow (refinement, the rotation's flow subtracted from the
# local network's, the flow triangulated under it), off.
WITHOUT_A_POSE = {**WITHOUT_AN_ENCODER_POSE, **{name: _DEFAULTS[name] for name in POSE_READERS}}
# The architecture for a model given its pose (odometry, the essential matrix's): it reads
# that pose against the flow as the main job reads its encoder's.
ARCHITECTURE_GIVEN_POSE = {**ARCHITECTURE, **WITHOUT_AN_ENCODER_POSE}
# The architecture for a model without a pose, or without the flow.
ARCHITECTURE_WITHOUT_MOTION = {**ARCHITECTURE, **WITHOUT_A_POSE}
# The main job's training options (its other options: `TrainConfig`'s defaults).
TRAINING = {
    "steps": 2000,
    "eval_every": 1000,
    "learning_rate": 1e-3,
    "lr_schedule": "cosine",
    "warmup_steps": 100,
    **MOTION_WEIGHTS,
}


def warmup_that_fits(steps: int, warmup_steps: int, given: Collection[str] = ()) -> int:
    """The warm-up of a run of `steps`: `warmup_steps`, unless that is the recipe's
    default (not in `given`) and too long for the run (the cosine schedule needs fewer
    warm-up steps than steps): then the recipe's fraction of the run (100 of 2,000: 5%),
    rounded down. A value the user gave is kept, and checked as given."""
    if "warmup_steps" in given or warmup_steps < steps:
        return warmup_steps
    return steps * TRAINING["warmup_steps"] // TRAINING["steps"]


def motion_where_it_applies(
    model: str,
    model_config: dict[str, Any],
    weights: dict[str, float],
    given: Collection[str] = (),
) -> tuple[dict[str, Any], dict[str, float]]:
    """The recipe's ways of teaching g the motion, where they apply.

    They are defaults of the global-local model whose encoder infers a pose: a model
    without one (another model, a given pose, no global module) trains without the
    epipolar term and the teacher, and without the refinement and search of the
    encoder's pose (`WITHOUT_AN_ENCODER_POSE`); one without a pose as g or without the
    flow also without the rotation's flow subtracted and the flow triangulated
    (`WITHOUT_A_POSE`). A given pose keeps those: it is read as the encoder's would be.
    The command line's options (`given`: the option names given) are kept.

    Args:
      model, model_config: the run's model and its constructor arguments.
      weights: the motion weights (`MOTION_WEIGHTS`' names) the launch would use.
      given: the options the user gave explicitly.

    Returns:
      (model_config, weights) to train with.
    """
    infers = config_lib.infers_pose(model, model_config)
    weights = {name: value if infers or name in given else 0.0 for name, value in weights.items()}
    if model == "global_local":
        off = {}
        if not config_lib.refines_pose(model, model_config):
            off |= WITHOUT_AN_ENCODER_POSE
        if not config_lib.reads_pose(model, model_config):
            off |= WITHOUT_A_POSE
        off = {name: value for name, value in off.items() if name not in given}
        model_config = {**model_config, **off}
        # No refinement (asked for), no search of where to start it.
        if (
            not model_config.get("pose_refinement_steps", 1)
            and "pose_refinement_starts" not in given
        ):
            model_config["pose_refinement_starts"] = WITHOUT_AN_ENCODER_POSE[
                "pose_refinement_starts"
            ]
    return model_config, weights


def with_stored_architecture(
    workdir: str | Path,
    model: str,
    model_config: dict[str, Any],
    given: Collection[str] = (),
) -> tuple[dict[str, Any], dict[str, Any]]:
    """A relaunch of a workdir keeps its run's architecture: an option of the
    global-local model that the command line does not give (`given`) takes the stored
    value, not the launcher's default (which may have changed since the run began).

    Returns:
      (model_config to train with, the options kept from the workdir).
    """
    stored = workdir_lib.stored_architecture(workdir)
    if model != "global_local" or not stored or stored.get("model") != model:
        return model_config, {}
    kept = {
        name: stored[name]
        for name in model_config
        if name not in given and stored.get(name) is not None and stored[name] != model_config[name]
    }
    return {**model_config, **kept}, kept
