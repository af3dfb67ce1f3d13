"""A suite's tasks: each one's name, what its result depends on, what it needs first,
and how long it takes.

Tasks, in order: the classical references on each dataset (`classical/<dataset>`, a
minute each: the main table's reference rows come first), then every training run of
the paper's main experiments (`train/<run>`: train or resume, then evaluate on the test
split) in the order of `gld.paper.suite.suite_runs`, each analysis as soon as the runs it
reads have finished: the generated filters (`filters`), the qualitative predictions
(`qualitative`), the pose probe (`pose_probe`), triangulation with the probe's pose
(`triangulation_predicted_pose`), the flow-error curves (`flow_error`), where the main
run beats the classical pipeline pair by pair (`regimes`); then the paper's
remaining comparisons: the learned flow network (`flow_net`: trained on the exact flow,
its end-point error and speed against DIS), the runner-supervised and flow experiment's
runs, and the flow networks' end-point error after depth training (`flow_finetuning`).
A task's identity is what its result depends on; a result made with another one is
redone (`gld.paper.runner`).
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable
from typing import Any

from gld.paper import analyses, rate_check, run_configs
from gld.paper import suite as paper_suite
from gld.paper.training_runs import TrainingRuns

# Seconds per training step at 128x96, batch 16, on the 2-core CPU machine (the cpu
# suite's runs, evaluations included; `experiments.benchmark` times the bare steps), and
# of a pose-probe step: for the ETA only.
STEP_SECONDS = {
    "global_local": 0.27,
    "small_encdec": 0.45,
    "eigen": 0.5,
    "dispnet": 6.0,
    "fcrn": 5.0,
    "struct2depth": 0.6,
    "struct2depth_flow": 0.6,
    "global_local_flow_net": 0.55,
    "flow_net_head": 0.65,
    "pose_probe": 0.1,
    "flow_net": 0.21,
}
DEFAULT_STEP_SECONDS = 5.0

# The runs trained after the main experiments' analyses: the paper's remaining
# comparisons (the first of them and every later run).
FIRST_REMAINING_RUN = "struct2depth"


def step_seconds(model: str) -> float:
    return STEP_SECONDS.get(model, DEFAULT_STEP_SECONDS)


@dataclasses.dataclass(frozen=True)
class Task:
    """One task of a suite: what it runs, and what its result depends on."""

    name: str
    run: Callable[[], dict[str, Any]]
    identity: dict[str, Any]  # what the result depends on; a changed one redoes the task
    seconds: float  # estimated, for the suite's ETA
    needs: tuple[str, ...] = ()


def _config_identity(config) -> dict[str, Any]:
    """A training run's identity: its whole configuration but the resolution, which the
    dataset fixes."""
    values = dataclasses.asdict(config)
    values.pop("height"), values.pop("width")
    return values


def suite_tasks(runner: TrainingRuns) -> list[Task]:
    """Every task of the suite of `runner`, in order. A task's identity is what its result
    depends on: a training run's whole configuration; an analysis's options and the
    identities of the results it reads."""
    tasks: list[Task] = []
    identities: dict[str, dict[str, Any]] = {}

    def add(name, run, identity, seconds, needs=(), inputs=None):
        # `inputs`: the needs whose identities are this task's too (default: all).
        inputs = needs if inputs is None else inputs
        identity = {**identity, "inputs": {need: identities[need] for need in inputs}}
        identities[name] = identity
        tasks.append(Task(name, run, identity, seconds, tuple(needs)))

    def add_runs(runs, then):
        for run in runs:
            # A flow network's run enters by the identity of the `flow_net` task.
            needs = ["flow_net"] if run.model in paper_suite.FLOW_NET_MODELS else []
            rated = runner.rated(run)
            config = run_configs.run_config(
                runner.scale, rated or run, height=0, width=0, flow_net_workdir="<flow_net>"
            )
            identity = _config_identity(config) | runner.version_of(config.dataset)
            inputs = list(needs)
            if run.rate_of is not None:
                # Its rate is its model's compared one: the check's runs come first,
                # and its identity holds the rate they chose (a placeholder before).
                needs += [f"train/{n}" for n in rate_check.rate_runs(runner.scale, run.rate_of)]
                if rated is None:
                    identity["learning_rate"] = f"the compared rate of {run.rate_of}"
            add(
                f"train/{run.name}",
                lambda run=run: runner.train_and_score(run),
                identity,
                run_configs.run_steps(runner.scale, run) * step_seconds(run.model) + 30,
                needs=needs,
                inputs=inputs,
            )
            then()

    for dataset in (runner.scale.dataset, runner.scale.varying_dataset):
        add(
            f"classical/{dataset.split('/')[-1]}",
            lambda dataset=dataset: analyses.classical(runner, dataset, analyses.CLASSICAL),
            {"dataset": dataset, "methods": list(analyses.CLASSICAL)} | runner.version_of(dataset),
            60,
        )
    probe = {
        "steps": runner.scale.probe_steps,
        "batch_size": runner.scale.batch_size,
        "learning_rate": runner.scale.learning_rate,
    }
    # The analyses, each made as soon as the runs it reads have finished (their
    # checkpoints are then at hand; where they are not, `TrainingRuns.trained` retrains them).
    waiting = [
        (
            "filters",
            functools.partial(analyses.filters, runner),
            {"pairs": analyses.FILTER_PAIRS},
            20,
            [f"train/{analyses.MAIN_RUN}"],
        ),
        (
            "qualitative",
            functools.partial(analyses.qualitative, runner),
            {"pairs": runner.scale.figure_pairs},
            60,
            [
                f"train/{run}"
                for name in analyses.QUALITATIVE_RUNS
                for run in rate_check.rate_runs(runner.scale, name)
            ],
        ),
        (
            "pose_probe",
            functools.partial(analyses.pose_probe, runner),
            probe,
            (4 + 2) * runner.scale.probe_steps * step_seconds("pose_probe") + 60,
            [f"train/{name}" for name in analyses.PROBED_RUNS],
        ),
        (
            "triangulation_predicted_pose",
            functools.partial(analyses.triangulation_predicted_pose, runner),
            {"pose_of": analyses.PREDICTED_POSE},
            30,
            ["pose_probe"],
        ),
        (
            "flow_error",
            functools.partial(analyses.flow_error, runner),
            {"pose_of": analyses.PREDICTED_POSE},
            60,
            [f"train/{analyses.MAIN_RUN}", "pose_probe"],
        ),
        (
            "regimes",
            functools.partial(analyses.regimes, runner),
            {"reference": analyses.REGIMES_REFERENCE, "bins": analyses.REGIMES_BINS},
            60,
            [
                f"classical/{runner.scale.dataset.split('/')[-1]}",
                *(f"train/{run}" for run in rate_check.rate_runs(runner.scale, analyses.MAIN_RUN)),
            ],
        ),
    ]
    if runner.scale.further:
        waiting.append(
            (
                "flow_finetuning",
                functools.partial(analyses.flow_finetuning, runner),
                {"runs": list(paper_suite.FLOW_EXPERIMENT[1:])},
                60,
                ["flow_net", *(f"train/{n}" for n in paper_suite.FLOW_EXPERIMENT[1:])],
            )
        )

    def add_ready():
        for analysis in list(waiting):
            if all(need in identities for need in analysis[4]):
                waiting.remove(analysis)
                add(*analysis)

    names = list(runner.runs)
    remaining = names.index(FIRST_REMAINING_RUN) if runner.scale.further else len(names)
    add_runs([runner.runs[name] for name in names[:remaining]], add_ready)
    if runner.scale.further:  # the paper's remaining comparisons
        flow_config = run_configs.flow_net_config(runner.scale, height=0, width=0)
        add(
            "flow_net",
            functools.partial(analyses.flow_net, runner),
            {**dataclasses.asdict(flow_config), "dis_timed_pairs": analyses.DIS_TIMED_PAIRS},
            runner.scale.flow_net_steps * step_seconds("flow_net") + 60,
        )
        add_runs([runner.runs[name] for name in names[remaining:]], add_ready)
    assert not waiting, f"analyses whose runs are not in the suite: {waiting}"
    return tasks
