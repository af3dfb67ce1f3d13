"""The main job's recipe and the run policy every launch applies."""

import json

import pytest

from gld.models import registry
from gld.runs import config, recipe


def test_the_recipe_is_a_valid_run():
    run = config.TrainConfig(model_config=recipe.ARCHITECTURE, **recipe.TRAINING).validate()
    assert config.refines_pose(run.model, run.model_config)
    assert run.epipolar_weight > 0 and run.pose_teacher_weight > 0


def test_the_warmup_fits_any_run_unless_given():
    default = recipe.TRAINING["warmup_steps"]
    assert recipe.warmup_that_fits(recipe.TRAINING["steps"], default) == default
    assert recipe.warmup_that_fits(94_000, default) == default
    assert recipe.warmup_that_fits(default + 1, default) == default
    # Too long for the run: the recipe's 5% of it, a valid cosine schedule at any length.
    for steps in (1, 19, 20, 50, default):
        warmup = recipe.warmup_that_fits(steps, default)
        assert warmup == steps // 20
        config.TrainConfig(**{**recipe.TRAINING, "steps": steps, "warmup_steps": warmup}).validate()
    # Given, it is kept (and refused by the schedule's check as given).
    assert recipe.warmup_that_fits(50, default, given={"warmup_steps"}) == default


def _main_job(model: str, given: dict) -> tuple[dict, dict]:
    """A launch's model options and motion weights, as the train launcher makes them:
    the recipe's, with what the command line gives over them."""
    model_config = (
        {**recipe.ARCHITECTURE, **{k: v for k, v in given.items() if k != "model"}}
        if model == "global_local"
        else {}
    )
    weights = {name: given.get(name, value) for name, value in recipe.MOTION_WEIGHTS.items()}
    model_config = {k: v for k, v in model_config.items() if k not in recipe.MOTION_WEIGHTS}
    return model_config, weights


REFINEMENT = recipe.ARCHITECTURE["pose_refinement_steps"]


@pytest.mark.parametrize(
    "given, teacher, epipolar, refinement, derotate, triangulate",
    [
        ({}, 1.0, 0.1, REFINEMENT, True, True),  # the main job
        ({"model": "small_encdec"}, 0.0, 0.0, None, None, None),  # no global parameters
        # A given pose: no encoder's to teach or refine; read against the flow as g.
        ({"global_source": "pose"}, 0.0, 0.0, 0, True, True),
        ({"global_source": "flow_pose"}, 0.0, 0.0, 0, True, True),
        ({"use_global_module": False}, 0.0, 0.0, 0, False, False),
        # The encoder infers g; refinement, derotation and triangulation read the flow.
        ({"use_flow": False}, 1.0, 0.1, 0, False, False),
        ({"global_dim": 4}, 0.0, 0.0, 0, False, False),  # g cannot stand for a pose
        ({"use_flow": False, "pose_refinement_steps": 3}, 1.0, 0.1, 3, False, False),  # kept
        ({"pose_refinement_steps": 0}, 1.0, 0.1, 0, True, True),  # no refinement, no search
        ({"use_global_module": False, "derotate_flow": True}, 0.0, 0.0, 0, True, False),  # refused
        ({"global_dim": 4, "parallax_depth": True}, 0.0, 0.0, 0, False, True),  # refused
        ({"model": "small_encdec", "pose_teacher_weight": 2.0}, 2.0, 0.0, None, None, None),
    ],
)
def test_the_main_jobs_motion_terms_apply_where_the_model_has_their_parts(
    given, teacher, epipolar, refinement, derotate, triangulate
):
    """The recipe teaches g the motion; a model without an encoder's pose (or without the
    flow) drops the teaching and the refinement, one without a pose as g (or without the
    flow) also the derotated and the triangulated flow, unless the command line names
    them (and then the config check says what is wrong)."""
    model = given.get("model", "global_local")
    model_config, weights = _main_job(model, given)
    model_config, weights = recipe.motion_where_it_applies(model, model_config, weights, given)
    assert weights == {"epipolar_weight": epipolar, "pose_teacher_weight": teacher}
    assert model_config.get("pose_refinement_steps") == refinement
    if refinement is not None:
        searches = recipe.ARCHITECTURE["pose_refinement_starts"] if refinement == REFINEMENT else 1
        assert model_config["pose_refinement_starts"] == searches
    assert model_config.get("derotate_flow") == derotate
    assert model_config.get("parallax_depth") == triangulate
    kept = [name for name in ("derotate_flow", "parallax_depth") if name in given]
    if kept and not config.reads_pose(model, model_config):
        with pytest.raises(ValueError, match=kept[0]):
            registry.check_config(model, model_config)


def test_a_relaunch_keeps_the_workdirs_architecture_for_options_not_given(tmp_path):
    stored = {"model": "global_local", "encoder_norm": "none", "use_image_pair": True}
    (tmp_path / "config.json").write_text(json.dumps({"architecture": stored}))
    launched = registry.full_config("global_local", recipe.ARCHITECTURE)
    for given, encoder_norm in (({}, "none"), ({"encoder_norm"}, "instance")):
        kept_config, kept = recipe.with_stored_architecture(
            tmp_path, "global_local", launched, given
        )
        assert kept_config["encoder_norm"] == encoder_norm  # an option given wins
        assert kept_config["use_image_pair"] is True  # the recipe's is False
        assert kept["use_image_pair"] is True
        # An option the stored config predates reads as its run was trained.
        assert (
            kept_config["flow_scale"] == registry.FIELDS_ADDED_LATER["global_local"]["flow_scale"]
        )
    # A new workdir, or another model, takes the launch's options.
    assert recipe.with_stored_architecture(tmp_path / "new", "global_local", launched) == (
        launched,
        {},
    )
    assert recipe.with_stored_architecture(tmp_path, "dispnet", {}) == ({}, {})
