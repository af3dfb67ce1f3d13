"""The suite runner's bookkeeping: which tasks a selection names, when a result is reused,
and what it reads from a run's metrics log."""

import json

import pytest

from gld.paper import runner as paper_runner
from gld.paper import suite as paper_suite
from gld.paper.suite import SUITES


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


def test_a_suite_without_the_further_runs_has_no_flow_network_task(tmp_path):
    full = [task.name for task in _runner(tmp_path / "full").tasks()]
    lean = [task.name for task in _runner(tmp_path / "lean", "cpu").tasks()]
    runs = paper_suite.suite_runs(SUITES["cpu"])
    assert [n for n in lean if n.startswith("train/")] == [f"train/{r.name}" for r in runs]
    # The main experiments' tasks in the full suite's order; no flow network, no
    # fine-tuning analysis; the suite ends with its last run.
    assert lean == [n for n in full if n in lean]
    assert "flow_net" not in lean and "flow_finetuning" not in lean
    assert lean[-1] == "train/eigen_varying"


def test_a_result_is_reused_only_with_the_same_identity(tmp_path):
    runner = _runner(tmp_path)
    task = next(t for t in runner.tasks() if t.name == "filters")
    assert not runner._done(task)
    path = paper_runner.result_path(tmp_path / "results", task.name)
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
        path = paper_runner.result_path(tmp_path / "results", name)
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


def test_the_flow_networks_runs_depend_on_the_flow_network_not_its_path(tmp_path):
    import dataclasses

    def tasks(scale, workdir):
        runner = paper_runner.SuiteRunner(scale, workdir, None, print_fn=lambda _: None)
        return {task.name: task for task in runner.tasks()}

    before = tasks(SUITES["cpu_full"], tmp_path / "a")
    assert before["train/flow_net_finetuned"].needs == ("flow_net",)
    assert before["flow_finetuning"].needs == (
        "flow_net",
        "train/flow_net_fixed",
        "train/flow_net_finetuned",
        "train/flow_net_head",
    )
    assert not before["train/flow_dis"].needs
    # Another suite directory: the same identities.
    moved = tasks(SUITES["cpu_full"], tmp_path / "b")
    assert {n: t.identity for n, t in moved.items()} == {n: t.identity for n, t in before.items()}
    # Another flow network: its depth runs and the analysis of them are redone.
    after = tasks(dataclasses.replace(SUITES["cpu_full"], flow_net_steps=4000), tmp_path / "a")
    changed = {n for n in before if before[n].identity != after[n].identity}
    assert changed == {
        "flow_net",
        "train/flow_net_fixed",
        "train/flow_net_finetuned",
        "train/flow_net_head",
        "flow_finetuning",
    }
    runner = paper_runner.SuiteRunner(SUITES["tiny"], tmp_path, None, print_fn=lambda _: None)
    config = paper_suite.run_config(
        runner.scale,
        runner.runs["flow_net_finetuned"],
        height=48,
        width=64,
        flow_net_workdir=str(runner.flow_net_dir()),
    )
    assert config.model_config["flow_net_workdir"] == str(tmp_path / "runs" / "flow_net")
    assert config.model_config["flow_trainable"] is True
    assert config.model_config["global_local"] == {
        **paper_suite.MAIN_RECIPE_WITHOUT_MOTION,
        **SUITES["tiny"].global_local,
    }


def test_an_analysis_is_redone_when_a_run_it_reads_changes(tmp_path):
    import dataclasses

    def identities(scale):
        runner = paper_runner.SuiteRunner(scale, tmp_path, None, print_fn=lambda _: None)
        return {task.name: task.identity for task in runner.tasks()}

    before = identities(SUITES["cpu_full"])
    after = identities(dataclasses.replace(SUITES["cpu_full"], learning_rate=5e-4))
    assert before["train/global_local_1px"]["learning_rate"] == 1e-3
    for name in ("train/global_local_1px", "pose_probe", "flow_error", "filters", "qualitative"):
        assert before[name] != after[name], name
    # The references do not depend on any training run.
    assert before["classical/small"] == after["classical/small"]


def test_curves_and_training_time_from_the_metrics_log(tmp_path):
    lines = [
        {"step": 50, "split": "train", "depth_l1": 0.05, "grad_norm": 0.3, "steps_per_sec": 5.0},
        {"step": 100, "split": "train", "depth_l1": 0.04, "steps_per_sec": 2.5},
        {"step": 100, "split": "test", "abs_inv": 0.03, "abs_rel": 0.4, "s_rmse": 0.3},
        {"step": 150, "split": "train", "loss": 1.0},  # a self-supervised run's record
    ]
    (tmp_path / "metrics.jsonl").write_text("\n".join(json.dumps(line) for line in lines))
    curves, seconds = paper_runner._training_log(tmp_path)
    assert curves == {
        "train": [[50, 0.05], [100, 0.04]],
        "loss": [[150, 1.0]],
        "grad_norm": [[50, 0.3]],
        "test": [[100, 0.03]],
    }
    assert seconds == pytest.approx(50 / 5.0 + 50 / 2.5)
    assert paper_runner._duration(59 * 60) == "59 min"
    assert paper_runner._duration(61 * 60 + 40) == "1 h 02 min"


def test_a_retrained_run_is_compared_with_its_result():
    assert paper_runner._reproduction("run", [0.1, 0.2], [0.1, 0.2 + 1e-9]) is None
    difference = paper_runner._reproduction("run", [0.1, 0.2], [0.1, 0.21])
    assert difference.startswith("run retrained scores 0.155, its result 0.15:")
    assert paper_runner._reproduction("run", [0.1, 0.2], [0.1]) is not None


def test_the_eta_counts_only_checkpoints_of_the_runs_present_configuration(tmp_path):
    """A run directory trained with other options is moved aside and trained afresh, so
    its checkpoints do not shorten the estimate (nor count as the run trained)."""
    import dataclasses

    from gld.runs import workdir as workdir_lib

    runner = _runner(tmp_path)
    run = runner.runs["dispnet_1px"]
    task = next(t for t in runner.tasks() if t.name == "train/dispnet_1px")
    steps = paper_suite.run_steps(runner.scale, run)
    full = steps * paper_runner.step_seconds("dispnet") + 30
    assert runner._remaining_seconds(task) == full
    run_dir = runner.run_dir(run.name)
    (run_dir / "checkpoints" / "100").mkdir(parents=True)
    config = paper_suite.run_config(runner.scale, run, height=96, width=128)
    workdir_lib.write_run_config(run_dir, config)
    assert (
        runner._remaining_seconds(task) == (steps - 100) * paper_runner.step_seconds("dispnet") + 30
    )
    # The same run logged less often: another configuration.
    (run_dir / "config.json").unlink()
    workdir_lib.write_run_config(run_dir, dataclasses.replace(config, log_every=50))
    assert runner._remaining_seconds(task) == full


def test_a_run_at_its_models_compared_rate_waits_for_the_check(tmp_path):
    runner = _runner(tmp_path)
    name = "train/small_encdec_dense"
    task = {t.name: t for t in runner.tasks()}[name]
    checks = ["train/small_encdec_1px", "train/small_encdec_1px_low_lr"]
    assert set(checks) <= set(task.needs)
    assert task.identity["learning_rate"] == "the compared rate of small_encdec_1px"
    assert task.identity["inputs"] == {}  # the chosen rate is the identity, not the check's
    for check, loss in zip(checks, (0.05, 0.04), strict=True):
        path = paper_runner.result_path(tmp_path / "results", check)
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps({"curves": {"train": [[10, loss]] * 8}}))
    task = {t.name: t for t in runner.tasks()}[name]
    assert task.identity["learning_rate"] == SUITES["cpu_full"].check_learning_rate
    assert task.identity["gt_pixels"] == 0
