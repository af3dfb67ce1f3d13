"""The run configuration: one definition of every training option."""

import copy
import dataclasses

import pytest
from absl import flags

from gld import options
from gld.runs import config, recipe


def test_every_option_has_help_and_valid_choices():
    fields = options.option_fields(config.TrainConfig)
    assert {field.name for field in fields} >= {"steps", "learning_rate", "flow_source", "seed"}
    for field in fields:
        assert field.metadata["help"].strip(), field.name
        choices = field.metadata["choices"]
        assert choices is None or field.default in choices, field.name
    # What the launcher sets from the data, not from a flag.
    settable = {field.name for field in fields}
    assert not settable & {"model_config", "dataset", "height", "width"}


def test_launcher_flags_are_derived_from_the_config():
    import experiments.train  # noqa: F401  (defines the trainer's flags)
    from experiments import common

    for field in options.option_fields(config.TrainConfig):
        flag = flags.FLAGS[field.name]
        assert flag.help.endswith(field.metadata["help"])
        assert flag.default == recipe.TRAINING.get(field.name, field.default), field.name
    try:
        flags.FLAGS(["train", "--learning_rate=0.5", "--flow_source=gt", "--seed=3"])
        given = common.training_options()
    finally:
        flags.FLAGS.unparse_flags()
    assert set(given) == {field.name for field in options.option_fields(config.TrainConfig)}
    built = config.TrainConfig(**given)
    assert (built.learning_rate, built.flow_source, built.seed) == (0.5, "gt", 3)
    assert built.checkpoint_every == config.TrainConfig().checkpoint_every  # one default


def test_a_launcher_default_must_name_an_option():
    from experiments import common

    with pytest.raises(ValueError, match="stepz"):
        common.define_training_flags(stepz=3)
    with pytest.raises(ValueError, match="encoder_normz"):
        common.define_architecture_flags(encoder_normz="instance")


def test_a_stored_config_is_read_whatever_version_wrote_it():
    current = dataclasses.asdict(config.TrainConfig(flow_source="gt", steps=5))
    old = dict(current)
    old["flow"] = old.pop("flow_source")
    old["model_config"] = {}
    loaded = config.from_stored(old)
    assert (loaded.flow_source, loaded.steps) == ("gt", 5)
    # Model options added after the first runs take the values those runs trained with.
    assert loaded.model_config["flow_scale"] == 1.0


@pytest.mark.parametrize(
    ("values", "named"),
    [
        ({"learning_rate": -0.01}, "learning_rate must be above 0"),
        ({"learning_rate": float("nan")}, "learning_rate must be finite"),
        ({"steps": -5}, "steps must be at least 1"),
        ({"log_every": 0}, "log_every must be at least 1"),
        ({"checkpoint_every": 0}, "checkpoint_every must be at least 1"),
        ({"eval_every": -1}, "eval_every must be at least 0"),
        ({"model": "foo"}, "model must be one of"),
        ({"flow_source": "exact"}, "flow_source must be one of"),
        ({"lr_schedule": "cosine", "steps": 10, "warmup_steps": 10}, "warmup_steps"),
        ({"model_config": {"global_dim": 0}}, "global_dim must be at least 1"),
        ({"model_config": {"bank_channels": [20, 0, 20]}}, r"bank_channels must be .*every item"),
        ({"model_config": {"flow_scale": 0.0}}, "flow_scale must be above 0"),
        ({"model_config": {"encoder_strides": [2, 2]}}, "same length"),
        ({"model_config": {"global_norm": "layer"}}, "global_norm must be one of"),
        ({"model_config": {"globl_dim": 3}}, "no option"),
        ({"epipolar_weight": -1.0}, "epipolar_weight must be at least 0"),
        ({"epipolar_weight": 0.1, "model_config": {"global_dim": 4}}, "stand for a pose"),
        ({"epipolar_weight": 0.1, "model_config": {"use_global_module": False}}, "stand for"),
        ({"epipolar_weight": 0.1, "model_config": {"global_source": "pose"}}, "stand for"),
        ({"epipolar_weight": 0.1, "model": "small_encdec"}, "stand for a pose"),
    ],
)
def test_validate_names_the_option_that_cannot_give_a_sound_run(values, named):
    with pytest.raises(ValueError, match=named):
        config.TrainConfig(**values).validate()


@pytest.mark.parametrize(
    "values",
    [
        {},
        {"model_config": recipe.ARCHITECTURE, **recipe.TRAINING},
        {"eval_every": 0, "model": "dispnet"},
        # Every bound is inclusive: the values on the bounds give a sound run.
        {
            "steps": 1,
            "log_every": 1,
            "checkpoint_every": 1,
            "keep_checkpoints": 1,
            "eval_every": 0,
            "gt_pixels": 0,
            "seed": 0,
            "depth_weight": 0.0,
            "smoothness_weight": 0.0,
            "model_config": {"global_dim": 1, "bank_channels": [1], "encoder_strides": [1] * 5},
        },
        # The pose terms apply to the paper's model, whose six global parameters are a pose.
        {"epipolar_weight": 0.1, "pose_teacher_weight": 0.1},
    ],
    ids=["defaults", "main_job", "no_evaluation", "on_the_bounds", "pose_terms"],
)
def test_a_sound_run_is_accepted_unchanged(values):
    run = config.TrainConfig(**values)
    before = copy.deepcopy(dataclasses.asdict(run))
    assert run.validate() is run
    assert dataclasses.asdict(run) == before  # validate checks; it changes no value


def test_the_epipolar_term_applies_to_global_parameters_that_are_inferred_poses():
    assert config.infers_pose("global_local", {})
    assert not config.infers_pose("global_local", {"global_dim": 4})
    assert not config.infers_pose("global_local", {"global_source": "pose"})
    assert not config.infers_pose("global_local", {"use_global_module": False})
    assert not config.infers_pose("small_encdec", {})
