"""A training run in its workdir, trained once and scored: the orchestration that a
comparison of methods (`gld.analysis.comparison`) and the paper's suite
(`gld.paper.training_runs`) share.

    seconds = train_unless_finished("dispnet", config, run_dir, train_source, test_source)
    scored = score(run_dir, test_source)   # its per-example metrics and parameters

A run whose newest checkpoint (`gld.runs.checkpoints.last_checkpointed_step`) has
reached its configuration's steps has finished and is reused, not trained again; an
unfinished one is trained, resuming from its newest intact checkpoint. Either way it goes
through `gld.training.trainer.train_and_evaluate`, so a finished run's stored config is
checked against the present one (another architecture or dataset is refused, other
options are named) and its checkpoint verified (a damaged newest step is moved aside and
trained again).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path
from typing import NamedTuple

import numpy as np

from gld.evaluation import evaluate as evaluation
from gld.models import registry
from gld.runs import checkpoints as checkpoint_lib
from gld.runs import workdir as workdir_lib
from gld.runs.config import TrainConfig
from gld.training import trainer


def train_unless_finished(
    name: str,
    config: TrainConfig,
    workdir: str | Path,
    train_source,
    test_source=None,
    *,
    progress: bool = True,
    print_fn: Callable[[str], None] = print,
) -> float | None:
    """Trains the run `name` in `workdir` (resuming it) unless it has finished.

    Args:
      name: the run's name in the messages.
      config: the run; it has finished once a checkpoint reaches `config.steps`.
      workdir, train_source, test_source, progress, print_fn: as
        `gld.training.trainer.train_and_evaluate` takes them.

    Returns:
      The seconds spent training, or None when the finished run is reused.
    """
    workdir = Path(workdir)
    started = time.perf_counter()
    done = checkpoint_lib.last_checkpointed_step(workdir)
    finished = done >= config.steps
    if finished:
        print_fn(f"{name}: reusing the finished run in {workdir} (step {done})")
    else:
        print_fn(f"{name}: training {config.steps} steps in {workdir}")
    trainer.train_and_evaluate(
        config, workdir, train_source, test_source, progress=progress, print_fn=print_fn
    )
    return None if finished else time.perf_counter() - started


class Scored(NamedTuple):
    """A trained run scored on a split."""

    per_example: dict[str, np.ndarray]  # name -> [N] values, with "example_mask"
    parameters: int  # the model's, in total
    config: TrainConfig  # the run's, as its workdir stores it


def score(
    workdir: str | Path,
    source,
    *,
    batch_size: int | None = None,
    flow_source: str | None = None,
    max_examples: int = 0,
    truth: evaluation.Truth | None = None,
) -> Scored:
    """Scores the trained run of `workdir` (its newest intact checkpoint) on `source`
    with the one evaluation loop (`gld.evaluation.evaluate.evaluate_source`).

    Args:
      batch_size, flow_source: the evaluation's (default: the run's own).
      max_examples: the first N examples only (0 = all).
      truth: the checked ground truth looked up by example id (None: the records').
    """
    model, variables, saved = workdir_lib.load_trained(workdir)
    per_example, _ = evaluation.evaluate_source(
        model,
        variables,
        source,
        batch_size=saved.eval_batch_size if batch_size is None else batch_size,
        flow_source=saved.flow_source if flow_source is None else flow_source,
        max_examples=max_examples,
        truth=truth,
    )
    return Scored(per_example, registry.parameter_counts(variables["params"])["total"], saved)
