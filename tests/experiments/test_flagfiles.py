"""Every flagfile parses with the trainer's flags and names a dataset gld can build."""

from pathlib import Path

import pytest
from absl import flags
from conftest import REPO_ROOT, run_python

import data
from gld.models import registry

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
        assert train_flags.encoder_norm == "none"  # the paper's global module
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


FLOW_FLAGFILES = sorted((REPO_ROOT / "experiments" / "flags" / "flow").glob("*.flags"))
FLOW_PARSE = """
import sys
from absl import flags
import data
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
    main_job = {"encoder_norm": "instance", "use_image_pair": False, "pose_refinement_steps": 10}
    for name, (default, _, _) in registry.architecture_options().items():
        expected = main_job.get(name, default)
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


def test_a_relaunch_takes_the_workdirs_architecture_for_options_no_flag_gives(
    train_flags, tmp_path
):
    import json

    from experiments import common
    from experiments import train as train_launcher

    architecture = {"model": "global_local", "encoder_norm": "none", "use_image_pair": True}
    (tmp_path / "config.json").write_text(json.dumps({"architecture": architecture}))
    for given, encoder_norm in (([], "none"), (["--encoder_norm=instance"], "instance")):
        try:
            train_flags(["train", f"--workdir={tmp_path}", *given])
            options = common.model_options("global_local")
            options = train_launcher._with_stored_architecture(options)
        finally:
            train_flags.unparse_flags()
        assert options["encoder_norm"] == encoder_norm  # a flag given wins
        assert options["use_image_pair"] is True  # the trainer's default is False
        # An option the stored config predates reads as its run was trained.
        assert options["flow_scale"] == registry.FIELDS_ADDED_LATER["global_local"]["flow_scale"]
    # A new workdir takes the trainer's defaults.
    try:
        train_flags(["train", f"--workdir={tmp_path / 'new'}"])
        options = train_launcher._with_stored_architecture(common.model_options("global_local"))
    finally:
        train_flags.unparse_flags()
    assert (options["encoder_norm"], options["use_image_pair"]) == ("instance", False)


@pytest.mark.parametrize(
    "given, teacher, epipolar, refinement",
    [
        ([], 1.0, 0.1, 10),  # the main job
        (["--model=small_encdec"], 0.0, 0.0, None),  # no global parameters to teach
        (["--global_source=pose"], 0.0, 0.0, 0),  # a given pose: no encoder's to refine
        (["--nouse_global_module"], 0.0, 0.0, 0),
        (["--nouse_flow"], 1.0, 0.1, 0),  # the encoder infers g; refinement reads the flow
        (["--global_dim=4"], 0.0, 0.0, 0),  # g cannot stand for a pose
        (["--nouse_flow", "--pose_refinement_steps=3"], 1.0, 0.1, 3),  # asked for: kept
        (["--model=small_encdec", "--pose_teacher_weight=2"], 2.0, 0.0, None),
    ],
)
def test_the_main_jobs_motion_terms_apply_where_the_model_has_their_parts(
    train_flags, given, teacher, epipolar, refinement
):
    """The trainer's defaults teach g the motion; a model without an encoder's pose (or
    without the flow, for refinement) drops them unless the command line names them (and
    then the config check says what is wrong)."""
    from experiments import common
    from experiments import train as train_launcher

    try:
        train_flags(["train", *given])
        options = common.model_options(train_flags.model)
        options, weights = train_launcher._motion_where_it_applies(options)
    finally:
        train_flags.unparse_flags()
    assert weights == {"epipolar_weight": epipolar, "pose_teacher_weight": teacher}
    assert options.get("pose_refinement_steps") == refinement
