"""A suite's tasks: their order, what each waits for, and what its identity holds (a
changed identity redoes the task)."""

import json

from gld.paper import suite as paper_suite
from gld.paper.result_files import result_path
from gld.paper.run_configs import run_config
from gld.paper.scales import SUITES
from gld.paper.tasks import suite_tasks
from gld.paper.training_runs import TrainingRuns
from gld.runs import recipe


def _runs(workdir, scale=SUITES["cpu_full"]):
    def no_data(dataset):
        raise AssertionError(f"{dataset} must not be loaded to list tasks")

    return TrainingRuns(scale, workdir, no_data, print_fn=lambda _: None)


def _tasks(workdir, suite="cpu_full"):
    return suite_tasks(_runs(workdir, SUITES[suite]))


def test_a_suite_without_the_further_runs_has_no_flow_network_task(tmp_path):
    full = [task.name for task in _tasks(tmp_path / "full")]
    lean = [task.name for task in _tasks(tmp_path / "lean", "cpu")]
    runs = paper_suite.suite_runs(SUITES["cpu"])
    assert [n for n in lean if n.startswith("train/")] == [f"train/{r.name}" for r in runs]
    # The main experiments' tasks in the full suite's order; no flow network, no
    # fine-tuning analysis; the suite ends with its last run.
    assert lean == [n for n in full if n in lean]
    assert "flow_net" not in lean and "flow_finetuning" not in lean
    assert lean[-1] == "train/eigen_varying"


def test_the_flow_networks_runs_depend_on_the_flow_network_not_its_path(tmp_path):
    import dataclasses

    def tasks(scale, workdir):
        return {task.name: task for task in suite_tasks(_runs(workdir, scale))}

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
    runs = _runs(tmp_path, SUITES["tiny"])
    config = run_config(
        runs.scale,
        runs.runs["flow_net_finetuned"],
        height=48,
        width=64,
        flow_net_workdir=str(runs.flow_net_dir()),
    )
    assert config.model_config["flow_net_workdir"] == str(tmp_path / "runs" / "flow_net")
    assert config.model_config["flow_trainable"] is True
    assert config.model_config["global_local"] == {
        **recipe.ARCHITECTURE_WITHOUT_MOTION,
        **SUITES["tiny"].global_local,
    }


def test_an_analysis_is_redone_when_a_run_it_reads_changes(tmp_path):
    import dataclasses

    def identities(scale):
        return {task.name: task.identity for task in suite_tasks(_runs(tmp_path, scale))}

    before = identities(SUITES["cpu_full"])
    after = identities(dataclasses.replace(SUITES["cpu_full"], learning_rate=5e-4))
    assert before["train/global_local_1px"]["learning_rate"] == 1e-3
    for name in ("train/global_local_1px", "pose_probe", "flow_error", "filters", "qualitative"):
        assert before[name] != after[name], name
    # The references do not depend on any training run.
    assert before["classical/small"] == after["classical/small"]


def test_a_run_at_its_models_compared_rate_waits_for_the_check(tmp_path):
    runs = _runs(tmp_path)
    name = "train/small_encdec_dense"
    task = {t.name: t for t in suite_tasks(runs)}[name]
    checks = ["train/small_encdec_1px", "train/small_encdec_1px_low_lr"]
    assert set(checks) <= set(task.needs)
    assert task.identity["learning_rate"] == "the compared rate of small_encdec_1px"
    assert task.identity["inputs"] == {}  # the chosen rate is the identity, not the check's
    for check, loss in zip(checks, (0.05, 0.04), strict=True):
        path = result_path(tmp_path / "results", check)
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps({"curves": {"train": [[10, loss]] * 8}}))
    task = {t.name: t for t in suite_tasks(runs)}[name]
    assert task.identity["learning_rate"] == SUITES["cpu_full"].check_learning_rate
    assert task.identity["gt_pixels"] == 0
