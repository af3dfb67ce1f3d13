"""The suites: each one's data and budget (`Scale`), by name (`SUITES`, `--suite`).

A suite is a scale — dataset, resolution, budget — over the one list of runs of
`gld.paper.suite`. Every learned model of a suite gets the same pipeline, loss,
optimiser, learning rate, schedule and budget, except the two large baselines (DispNet,
FCRN: `LARGE_MODELS`), whose budget (`Scale.large_steps`) is the largest the suite's
machine affords; the report says so.
"""

from __future__ import annotations

import dataclasses
from typing import Any

DENSITIES = (1, 4, 16, 64, 0)  # supervised pixels per image; 0 = dense
LARGE_MODELS = ("dispnet", "fcrn")


@dataclasses.dataclass(frozen=True)
class Scale:
    """A suite's data and budget.

    Attributes:
      name: the suite's name (`--suite`).
      dataset, varying_dataset: TFDS names of the benchmark and of its varying-intrinsics
        config.
      steps: training steps of every learned model but the large ones.
      large_steps: training steps of DispNet and FCRN.
      batch_size, learning_rate: Adam's batch and peak rate (cosine decay to 1%).
      check_learning_rate: the second peak rate of the main table's learning-rate check
        (None: no check).
      warmup_fraction: linear warm-up, as a fraction of a run's steps.
      curve_evaluations: test evaluations over training of the runs of the over-fitting
        figure (the main global-local run and the large baselines).
      curve_examples: test pairs of those evaluations (0 = all).
      probe_steps: training steps of each pose-probe setting.
      flow_net_steps: training steps of the learned flow network (batch 8).
      large_densities: the supervision densities DispNet is trained at.
      global_local: extra options of every global-local run (e.g. a smaller encoder).
      figure_pairs: test pairs of the qualitative grid.
      further: the runs beyond the paper's main experiments: the one-fixed-pixel control
        of the densities, the self-supervised baseline and the flow experiment.
      hours: what the suite takes on the machine it was sized for, for the report.
    """

    name: str
    dataset: str
    varying_dataset: str
    steps: int
    large_steps: int
    batch_size: int = 16
    learning_rate: float = 1e-3
    check_learning_rate: float | None = None
    warmup_fraction: float = 0.05
    curve_evaluations: int = 8
    curve_examples: int = 0
    probe_steps: int = 2000
    flow_net_steps: int = 5000
    large_densities: tuple[int, ...] = DENSITIES
    global_local: dict[str, Any] = dataclasses.field(default_factory=dict)
    figure_pairs: int = 4
    further: bool = True
    hours: str = ""


SUITES: dict[str, Scale] = {
    # The paper's main experiments in about 5 hours on the 2-core CPU machine at 128x96
    # (step times: experiments.benchmark): half of cpu_full's budget, no further runs;
    # DispNet and FCRN 60 steps, and the over-fitting curves on 50 test pairs (a DispNet
    # evaluation of all 200 takes 40 s, as long as 7 of its steps).
    "cpu": Scale(
        name="cpu",
        dataset="gld_scenes/small",
        varying_dataset="gld_scenes/small_varying",
        steps=1000,
        large_steps=60,
        check_learning_rate=3e-4,
        curve_examples=50,
        probe_steps=1000,
        large_densities=(1, 0),
        further=False,
        hours="about 5 hours on 2 CPU cores (DispNet: 5.7 s a step, FCRN: 4.8 s)",
    ),
    # Every run at twice the cpu suite's budget, with the further runs: about 11 hours.
    "cpu_full": Scale(
        name="cpu_full",
        dataset="gld_scenes/small",
        varying_dataset="gld_scenes/small_varying",
        steps=2000,
        large_steps=150,
        check_learning_rate=3e-4,
        large_densities=(1, 0),
        hours="about 11 hours on 2 CPU cores (DispNet: 5.7 s a step, FCRN: 4.8 s)",
    ),
    # The paper's scale: 256x192 and its 94K steps for every model, on a GPU or hosts.
    "paper": Scale(
        name="paper",
        dataset="gld_scenes/full",
        varying_dataset="gld_scenes/full_varying",
        steps=94_000,
        large_steps=94_000,
        learning_rate=3e-4,
        check_learning_rate=1e-4,
        warmup_fraction=0.01,
        curve_evaluations=20,
        curve_examples=200,
        probe_steps=20_000,
        flow_net_steps=50_000,
        hours="days on a CPU; about a day on one GPU",
    ),
    # A few steps on the tiny benchmark: the suite's machinery, not its numbers.
    "tiny": Scale(
        name="tiny",
        dataset="gld_scenes/tiny",
        varying_dataset="gld_scenes/tiny_varying",
        steps=4,
        large_steps=2,
        batch_size=4,
        check_learning_rate=3e-4,
        curve_evaluations=2,
        probe_steps=4,
        flow_net_steps=4,
        large_densities=(1, 0),
        global_local={"encoder_channels": [4, 8, 8, 8, 8]},
        figure_pairs=2,
        hours="about a minute",
    ),
}
