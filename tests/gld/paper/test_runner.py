"""The suite runner's bookkeeping: which tasks a selection names, when a result is reused,
and the suite's ETA."""

import json

import pytest

from gld.paper import runner as paper_runner
from gld.paper import suite as paper_suite
from gld.paper.result_files import result_path
from gld.paper.run_configs import run_config, run_steps
from gld.paper.scales import SUITES
from gld.paper.tasks import step_seconds


def _runner(tmp_path, suite="cpu_full"):
    def no_data(dataset):
        raise AssertionError(f"{dataset} must not be loaded to list or select tasks")

    return paper_runner.SuiteRunner(SUITES[suite], tmp_path, no_data, print_fn=lambda _: None)


def test_selection_by_name_and_group(tmp_path):
    runner = _runner(tmp_path)
    names = [task.name for task in runner.tasks()]
    runs = paper_suite.suite_runs(SUITES["cpu_full"])
    assert [n for n in names if n.startswith("train/")] == [f"train/{r.name}" for r in runs]
    # The main table's reference rows first: a minute each.
    assert names[:2] == ["classical/small", "classical/small_varying"]
    # Each analysis right after the last run it reads (its checkpoints are at hand).
    for analysis, after in (
        ("filters", "train/global_local_1px"),
        ("qualitative", "train/dispnet_1px_low_lr"),
        ("pose_probe", "train/global_local_no_epipolar"),
        ("triangulation_predicted_pose", "pose_probe"),
        ("flow_error", "triangulation_predicted_pose"),
        ("flow_finetuning", "train/flow_net_head"),
    ):
        assert names.index(analysis) == names.index(after) + 1, analysis
    # The main table (and its learning-rate check) before the other experiments.
    assert names.index("train/fcrn_1px") < names.index("train/global_local_image_pair")
    # The paper's remaining comparisons after the main experiments.
    assert names.index("flow_net") + 1 == names.index("train/struct2depth")
    assert names.index("flow_net") == names.index("train/eigen_varying") + 1
    assert names[-1] == "flow_finetuning"

    def selected(*only):
        return [task.name for task in runner.selected(list(only))]

    assert selected("classical") == ["classical/small", "classical/small_varying"]
    assert selected("classical/small") == ["classical/small"]
    assert selected("train/") == selected("train") == [n for n in names if n.startswith("train/")]
    assert selected("train/global_local_1px") == ["train/global_local_1px"]
    with pytest.raises(ValueError, match=r"unknown suite tasks \['train/global'\]"):
        runner.selected(["train/global"])


def test_a_result_is_reused_only_with_the_same_identity(tmp_path):
    runner = _runner(tmp_path)
    task = next(t for t in runner.tasks() if t.name == "filters")
    assert not runner._done(task)
    path = result_path(tmp_path / "results", task.name)
    path.parent.mkdir(parents=True)
    path.write_text(json.dumps({"identity": task.identity}))
    assert runner._done(task)
    assert set(runner.finished()) == {"filters"}
    path.write_text(json.dumps({"identity": {**task.identity, "pairs": 3}}))
    assert not runner._done(task) and runner.finished() == {}


def test_a_result_made_on_another_version_of_the_data_is_redone(tmp_path):
    def no_data(dataset):
        raise AssertionError(f"{dataset} must not be loaded to list tasks")

    def runner(versions):
        return paper_runner.SuiteRunner(
            SUITES["cpu"],
            tmp_path,
            no_data,
            print_fn=lambda _: None,
            dataset_version=versions.__getitem__,
        )

    old = runner({"gld_scenes/small": "1.0.0", "gld_scenes/small_varying": "1.2.0"})
    new = runner({"gld_scenes/small": "2.0.0", "gld_scenes/small_varying": "2.0.0"})
    names = ("classical/small", "classical/small_varying", "train/global_local_1px")
    old_tasks = {task.name: task for task in old.tasks()}
    for name in names:
        path = result_path(tmp_path / "results", name)
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps({"identity": old_tasks[name].identity}))
    assert set(old.finished()) == set(names)
    # The training runs and classical methods read the data: none is reused.
    assert new.finished() == {}
    new_tasks = {task.name: task for task in new.tasks()}
    assert new_tasks["train/global_local_1px"].identity["dataset_version"] == "2.0.0"
    assert new_tasks["classical/small_varying"].identity["dataset_version"] == "2.0.0"
    # An analysis reads its runs' identities, versions included.
    assert new_tasks["filters"].identity != old_tasks["filters"].identity


def test_the_eta_counts_only_checkpoints_of_the_runs_present_configuration(tmp_path):
    """A run directory trained with other options is moved aside and trained afresh, so
    its checkpoints do not shorten the estimate (nor count as the run trained)."""
    import dataclasses

    from gld.runs import workdir as workdir_lib

    runner = _runner(tmp_path)
    run = runner.runs["dispnet_1px"]
    task = next(t for t in runner.tasks() if t.name == "train/dispnet_1px")
    steps = run_steps(runner.scale, run)
    full = steps * step_seconds("dispnet") + 30
    assert runner._remaining_seconds(task) == full
    run_dir = runner.run_dir(run.name)
    (run_dir / "checkpoints" / "100").mkdir(parents=True)
    config = run_config(runner.scale, run, height=96, width=128)
    workdir_lib.write_run_config(run_dir, config)
    assert runner._remaining_seconds(task) == (steps - 100) * step_seconds("dispnet") + 30
    # The same run logged less often: another configuration.
    (run_dir / "config.json").unlink()
    workdir_lib.write_run_config(run_dir, dataclasses.replace(config, log_every=50))
    assert runner._remaining_seconds(task) == full


def test_the_eta_in_hours_and_minutes():
    assert paper_runner._duration(59 * 60) == "59 min"
    assert paper_runner._duration(61 * 60 + 40) == "1 h 02 min"
