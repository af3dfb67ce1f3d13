"""Every flagfile parses with the trainer's flags and names a dataset gld can build."""

from pathlib import Path

import pytest
from absl import flags
from conftest import REPO_ROOT, run_python

import data
from experiments import common
from gld import options
from gld.models import registry
from gld.models.global_local import ABLATIONS, GlobalLocal
from gld.runs import recipe

FLAGFILES = sorted((REPO_ROOT / "experiments" / "flags").glob("*.flags"))


@pytest.fixture(scope="module")
def train_flags():
    import experiments.train  # noqa: F401  (defines the trainer's flags)

    return flags.FLAGS


def test_there_is_a_flagfile_per_result():
    names = {path.stem for path in FLAGFILES}
    for dataset in ("scenes11", "sun3d", "rgbd"):
        assert f"{dataset}_global_local" in names
    for ablation in ("no_image_pair", "no_coordconv", "no_global_module", "no_flow"):
        assert f"scenes11_ablation_{ablation}" in names


@pytest.mark.parametrize("path", FLAGFILES, ids=lambda p: p.stem)
def test_flagfile_parses_and_documents_itself(train_flags, path: Path):
    header = [line for line in path.read_text().splitlines() if line.startswith("#")]
    assert any("Command:" in line and path.name in line for line in header)
    try:
        train_flags(["train", f"--flagfile={path}"])
        data.parse_name(train_flags.dataset)
        assert train_flags.workdir.startswith("runs/")
        # The model the launcher would build from it passes the config check.
        given = {name for name in train_flags if train_flags[name].present}
        weights = {name: train_flags[name].value for name in recipe.MOTION_WEIGHTS}
        model_config, _ = recipe.motion_where_it_applies(
            train_flags.model, common.model_options(train_flags.model), weights, given
        )
        if "flow_net_workdir" in model_config:  # needs a trained flow network to check
            model_config = {"global_local": {}, **model_config}
            registry.check_config("global_local", model_config["global_local"])
        else:
            registry.check_config(train_flags.model, model_config)
    finally:
        train_flags.unparse_flags()


# The main job and the CPU-budget runs on gld_scenes/small (its longer run, the flow
# experiments) use the main job's recipe; the rest are the paper's.
def _main_job_recipe(path: Path) -> bool:
    return path.stem == "demo" or path.stem.startswith("gld_scenes_small_")


PAPER_FLAGFILES = [
    p for p in FLAGFILES if not p.stem.startswith("compare_") and not _main_job_recipe(p)
]


@pytest.mark.parametrize("path", PAPER_FLAGFILES, ids=lambda p: p.stem)
def test_paper_flagfiles_train_with_the_papers_optimiser(train_flags, path: Path):
    # The trainer's defaults are the main job's recipe; a paper experiment must say so.
    try:
        train_flags(["train", f"--flagfile={path}"])
        assert train_flags.learning_rate == 1e-4
        assert train_flags.lr_schedule == "constant"
        assert train_flags.epipolar_weight == 0  # the paper's loss
        assert train_flags.pose_teacher_weight == 0 and train_flags.pose_refinement_steps == 0
        assert train_flags.pose_refinement_starts == 1
        assert train_flags.encoder_norm == "none"  # the paper's global module
        # The paper's local network: zero padding, the flow as it is.
        assert train_flags.border == "zero"
        assert not train_flags.derotate_flow and not train_flags.parallax_depth
        assert train_flags.use_image_pair == (path.stem != "scenes11_ablation_no_image_pair")
    finally:
        train_flags.unparse_flags()


SCENES11 = [p for p in FLAGFILES if p.stem.startswith("scenes11_")]


@pytest.mark.parametrize("path", SCENES11, ids=lambda p: p.stem)
def test_scenes11_flagfiles_share_the_base_and_change_one_setting(train_flags, path: Path):
    base = REPO_ROOT / "experiments" / "flags" / "base" / "scenes11.flags"
    lines = [line for line in path.read_text().splitlines() if line.startswith("--")]
    assert lines[0] == "--flagfile=experiments/flags/base/scenes11.flags"
    assert len(lines) <= 3  # the base, the workdir and at most one change
    try:
        train_flags(["train", f"--flagfile={base}"])
        base_values = train_flags.flag_values_dict()
    finally:
        train_flags.unparse_flags()
    try:
        train_flags(["train", f"--flagfile={path}"])
        values = train_flags.flag_values_dict()
    finally:
        train_flags.unparse_flags()
    changed = {name for name in values if values[name] != base_values[name]}
    assert values["dataset"] == "demon/scenes11" and values["steps"] == 94_000
    assert changed - {"workdir", "flagfile"} == {line.split("=")[0][2:] for line in lines[2:]}


@pytest.mark.parametrize("name", sorted(ABLATIONS))
def test_each_ablation_flagfile_is_the_models_ablation_switch(train_flags, name):
    """The paper's ablations are defined once (`gld.models.global_local.ABLATIONS`); each
    flagfile sets that switch on the base and nothing else."""
    path = REPO_ROOT / "experiments" / "flags" / f"scenes11_ablation_{name}.flags"
    base = REPO_ROOT / "experiments" / "flags" / "base" / "scenes11.flags"
    try:
        train_flags(["train", f"--flagfile={base}"])
        base_values = train_flags.flag_values_dict()
        train_flags.unparse_flags()
        train_flags(["train", f"--flagfile={path}"])
        values = train_flags.flag_values_dict()
    finally:
        train_flags.unparse_flags()
    changed = {
        key: values[key]
        for key in values
        if values[key] != base_values[key] and key not in ("workdir", "flagfile")
    }
    assert changed == ABLATIONS[name]


FLOW_FLAGFILES = sorted((REPO_ROOT / "experiments" / "flags" / "flow").glob("*.flags"))
FLOW_PARSE = """
import sys
from absl import flags
import data
from experiments import common
from gld.models import global_local as model_lib
import experiments.train_flow  # noqa: F401  (defines the flow trainer's flags)
flags.FLAGS(["train_flow", "--flagfile=" + sys.argv[1]])
data.parse_name(flags.FLAGS.dataset)
assert flags.FLAGS.workdir.startswith("runs/"), flags.FLAGS.workdir
"""


@pytest.mark.parametrize("path", FLOW_FLAGFILES, ids=lambda p: p.stem)
def test_flow_flagfiles_parse_with_the_flow_trainer_and_document_themselves(path: Path):
    header = [line for line in path.read_text().splitlines() if line.startswith("#")]
    assert any("Command:" in line and "experiments.train_flow" in line for line in header)
    run_python(FLOW_PARSE, str(path))


def test_the_trainers_architecture_defaults_are_the_models_but_the_main_jobs(train_flags):
    for field in options.option_fields(GlobalLocal):
        name = field.name
        expected = recipe.ARCHITECTURE.get(name, field.default)
        expected = [str(item) for item in expected] if isinstance(expected, tuple) else expected
        assert train_flags[name].default == expected, name


def test_the_demo_flagfile_is_what_the_trainer_does_without_flags(train_flags):
    lines = (REPO_ROOT / "experiments" / "flags" / "demo.flags").read_text().splitlines()
    stated = [line for line in lines if line.startswith("--")]
    assert stated
    try:
        train_flags(["train", *stated])
        for line in stated:
            name = line[2:].split("=")[0]
            name = name[2:] if name not in train_flags and name.startswith("no") else name
            assert train_flags[name].value == train_flags[name].default, line
    finally:
        train_flags.unparse_flags()


def test_the_trainer_knows_which_options_the_command_line_gives(train_flags, tmp_path):
    """What `gld.runs.recipe`'s run policy keeps: the flags given, from the command line
    or a flagfile, and none of the defaults."""
    from experiments import train as train_launcher

    flagfile = tmp_path / "run.flags"
    flagfile.write_text("--pose_refinement_steps=3\n")
    try:
        train_flags(["train", "--nouse_flow", f"--flagfile={flagfile}"])
        given = train_launcher._given()
    finally:
        train_flags.unparse_flags()
    assert {"use_flow", "pose_refinement_steps"} <= given
    assert not given & {"encoder_norm", "epipolar_weight", "steps", "workdir"}
