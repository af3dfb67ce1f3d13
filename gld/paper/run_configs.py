"""A suite's run as the trainer's configuration: its budget, warm-up, logging and
checkpoints at the suite's scale (`run_config`), and the learned flow network's
(`flow_net_config`).

`gld.paper.runner` trains, reuses and scores the runs from these configurations; the
report reads a run's budget from them.
"""

from __future__ import annotations

from gld.paper.rate_check import TRAINING_RECORDS
from gld.paper.scales import LARGE_MODELS, Scale
from gld.paper.suite import FLOW_NET_MODELS, Run
from gld.runs import config, flow_config


def run_steps(scale: Scale, run: Run) -> int:
    """A run's training steps: the suite's, or the large models' budget."""
    return scale.large_steps if run.model in LARGE_MODELS else scale.steps


def warmup_steps(scale: Scale, steps: int) -> int:
    """The linear warm-up of a run of `steps` (at least one step, and fewer than `steps`)."""
    return max(1, round(steps * scale.warmup_fraction)) if steps > 1 else 0


def run_config(scale: Scale, run: Run, *, height: int, width: int, flow_net_workdir: str = ""):
    """The run's `gld.runs.config.TrainConfig` (validated); the models of `FLOW_NET_MODELS`
    start from the flow network of `flow_net_workdir` (which the trainer checks: the
    suite names it before the network is trained)."""

    steps = run_steps(scale, run)
    # A run's own options (an ablation's switch) win over the suite's.
    model_config = {**(scale.global_local if run.model == "global_local" else {})}
    model_config.update(run.model_config)
    if run.model == "global_local_flow_net":
        model_config["global_local"] = {**scale.global_local, **model_config["global_local"]}
    options = {
        "model": run.model,
        "model_config": model_config,
        "dataset": scale.varying_dataset if run.varying else scale.dataset,
        "height": height,
        "width": width,
        "steps": steps,
        "batch_size": scale.batch_size,
        "learning_rate": scale.learning_rate,
        "lr_schedule": "cosine",
        "warmup_steps": warmup_steps(scale, steps),
        "gt_pixels": 1,
        "checkpoint_every": max(1, min(250, steps // 4)),
        "log_every": max(1, min(50, steps // TRAINING_RECORDS)),
        "eval_every": max(1, steps // scale.curve_evaluations) if run.curve else 0,
        "eval_examples": scale.curve_examples if run.curve else 0,
        "seed": 0,
    }
    options.update(run.options)
    validated = config.TrainConfig(**options).validate()
    if run.model in FLOW_NET_MODELS:
        validated.model_config["flow_net_workdir"] = flow_net_workdir
    return validated


def flow_net_config(scale: Scale, *, height: int, width: int):
    """The learned flow network's `gld.runs.flow_config.FlowTrainConfig` (validated): its own
    recipe (`experiments/flags/flow/flow_net_small.flags`), trained on the exact flow of
    the suite's training pairs."""

    steps = scale.flow_net_steps
    return flow_config.FlowTrainConfig(
        dataset=scale.dataset,
        height=height,
        width=width,
        steps=steps,
        batch_size=8,
        learning_rate=1e-3,
        lr_schedule="cosine",
        warmup_steps=max(1, round(steps * 0.02)) if steps > 1 else 0,
        checkpoint_every=max(1, min(500, steps // 4)),
        eval_every=max(1, steps // 5),
        eval_examples=scale.curve_examples,
        seed=0,
    ).validate()
