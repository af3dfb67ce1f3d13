"""Runs a suite of `gld.paper.suite`: every task not done yet (`gld.paper.tasks`: the
classical references, the training runs and the analyses of `gld.paper.analyses`) in the
suite's order, with the suite's ETA; each result is a file (`gld.paper.result_files`),
so a killed suite continues where it stopped.

A task is skipped when its result exists and was made with the same configuration (its
identity); a training run whose result is missing resumes from its newest checkpoint
(`gld.paper.training_runs`). `gld.paper.report` turns the results into the report.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from typing import Any

import numpy as np

from gld.paper import result_files
from gld.paper.run_configs import run_steps
from gld.paper.tasks import Task, step_seconds, suite_tasks
from gld.paper.training_runs import TrainingRuns
from gld.runs.checkpoints import last_checkpointed_step


class SuiteRunner(TrainingRuns):
    """Builds a suite's tasks and runs those not done yet. It is the suite's
    `TrainingRuns` (its arguments are theirs), which the tasks train and the analyses
    read."""

    def tasks(self) -> list[Task]:
        """Every task of the suite, in order (`gld.paper.tasks.suite_tasks`)."""
        return suite_tasks(self)

    def selected(self, only: Sequence[str] | None = None) -> list[Task]:
        """The tasks named in `only` (a task's name, or a group: "train", "classical"),
        or all; ValueError naming any name that matches no task."""
        tasks = self.tasks()
        if not only:
            return tasks
        names = [task.name for task in tasks]
        unknown = [n for n in only if not any(_matches(t, n) for t in names)]
        if unknown:
            raise ValueError(f"unknown suite tasks {unknown}; valid: {names}")
        return [t for t in tasks if any(_matches(t.name, n) for n in only)]

    def finished(self) -> dict[str, dict[str, Any]]:
        """The results of every finished task made with the suite's present definition."""
        results = {}
        for task in self.tasks():
            result = result_files.read_result(self.results_dir, task.name)
            if result is not None and _same_identity(result, task):
                results[task.name] = result
        return results

    def run(self, only: Sequence[str] | None = None, *, commit: str = "") -> list[str]:
        """Runs every task not done yet (those named in `only`, if given; see
        `selected`). A task that fails is reported and the suite goes on.

        Training runs are collective (every process of a multi-process launch trains
        them); the classical baselines and analyses run in process 0, which alone
        writes results. Process 0 decides which tasks are pending.

        Returns:
          "<task>: <error>" for every task that failed.
        """
        import jax

        tasks = self.selected(only)
        by_name = {task.name: task for task in self.tasks()}
        done = [self._done(task) for task in tasks]
        if jax.process_count() > 1:
            from jax.experimental import multihost_utils

            done = [bool(d) for d in multihost_utils.broadcast_one_to_all(np.asarray(done))]
        pending = [task for task, finished in zip(tasks, done, strict=True) if not finished]
        for task, finished in zip(tasks, done, strict=True):
            if finished:
                path = result_files.result_path(self.results_dir, task.name)
                self.print(f"{task.name}: done (reused {path})")
        estimates = {task.name: self._remaining_seconds(task) for task in pending}
        spent, estimated, failures = 0.0, 0.0, []
        for index, task in enumerate(pending):
            pace = spent / estimated if estimated > 600 else 1.0
            remaining = sum(estimates[t.name] for t in pending[index:])
            eta = _duration(remaining * pace)
            self.print(f"[{index + 1}/{len(pending)}] {task.name} — suite ETA {eta}")
            collective = task.name.startswith("train/")
            if not collective and jax.process_index() != 0:
                continue
            missing = [need for need in task.needs if not self._done(by_name[need])]
            if missing:
                self.print(f"{task.name}: skipped, needs {missing} first")
                continue
            # Its identity again, now that the tasks before it have finished (a run whose
            # rate a learning-rate check of this launch chose).
            task = {t.name: t for t in self.tasks()}[task.name]
            started = time.perf_counter()
            self.differences = []
            try:
                result = task.run()
            except Exception as error:  # noqa: BLE001 - one failed task must not stop the rest
                failures.append(f"{task.name}: {type(error).__name__}: {error}")
                self.print(f"{task.name}: FAILED ({failures[-1]}); going on with the others")
                continue
            seconds = time.perf_counter() - started
            result.update(task=task.name, identity=task.identity, seconds=seconds, commit=commit)
            if self.differences:
                result["retrained_differently"] = self.differences
            if jax.process_index() == 0:
                result_files.write_result(self.results_dir, task.name, result)
            spent += seconds
            estimated += estimates[task.name]
        return failures

    def _done(self, task: Task) -> bool:
        result = result_files.read_result(self.results_dir, task.name)
        return result is not None and _same_identity(result, task)

    def _remaining_seconds(self, task: Task) -> float:
        """The task's estimated seconds, less the steps its run has checkpointed."""
        if task.name == "flow_net":
            left = self.scale.flow_net_steps - last_checkpointed_step(self.flow_net_dir())
            return max(0, left) * step_seconds("flow_net") + 60
        if not task.name.startswith("train/"):
            return task.seconds
        run = self.runs[task.name.removeprefix("train/")]
        steps = run_steps(self.scale, run)
        left = max(0, steps - self.resumable_step(run))
        return left * step_seconds(run.model) + 30


def _same_identity(result: dict[str, Any], task: Task) -> bool:
    return result.get("identity") == result_files.as_stored(task.identity)


def _matches(task: str, name: str) -> bool:
    """Whether `name` selects `task`: its whole name, or a leading group of it."""
    return task == name or task.startswith(name.rstrip("/") + "/")


def _duration(seconds: float) -> str:
    minutes = round(seconds / 60)
    return f"{minutes // 60} h {minutes % 60:02d} min" if minutes >= 60 else f"{minutes} min"
