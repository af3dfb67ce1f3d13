"""The paper's experimental section as one list of runs: what each suite trains and scores.

A suite (`SUITES`) is a scale — dataset, resolution, budget — and `suite_runs` gives its
training runs: the main table's models at one pixel per image, the ablations, the
supervision densities, the given flow and given pose, and the varying intrinsics. Every
learned model of a suite gets the same pipeline, loss, optimiser, learning rate,
schedule and budget, except the two large baselines (DispNet, FCRN), whose budget
(`Scale.large_steps`) is the largest the suite's machine affords; the report says so.

One shared rate could suit one model and starve another (Eigen's network collapses at
the CPU suite's 1e-3, DispNet's too: the output saturates and the gradient vanishes), so
every learned model of the main table is also trained at a second, lower rate
(`Scale.check_learning_rate`, runs `<run>_low_lr`); the report shows both and compares
each model at the rate with the lower training loss (`compared_run`; never chosen on the
test split), and the over-fitting figure and the qualitative grid show that run. The
model's runs at the other densities and on the varying intrinsics train at that rate too
(`Run.rate_of`, `with_compared_rate`); the ablations, at the suite's rate (global-local's
check chose it on the CPU suite).

The global-local runs use the main job's recipe (`experiments/flags/demo.flags`): a
global encoder with instance normalisation that sees the flow alone, and a global
module that learns the motion: the epipolar term at 0.1, the classical pose teacher
(`pose_teacher_weight`) and ten refinement steps of the encoder's pose on the flow
(`pose_refinement_steps`). Two ablations therefore read differently from the paper's:
"+ image pair" adds the image pair the main recipe leaves out, and the runs without a
global module or without flow drop all three ways of learning the motion too (they need
g, and they read the flow); the run "- epipolar term, teacher and refinement" measures
what those alone cost (g learned from the depth loss alone, as the paper's). The runs
given a pose have no encoder to teach or refine.

A suite with the further runs (`Scale.further`; all but cpu) adds the control of one
fixed pixel per image to the densities, and closes with the paper's remaining
comparisons: the self-supervised baseline (Struct2Depth, with and without flow; no depth
labels) in the main table and its learning-rate check, and the flow experiment. That
one trains the learned flow network on the exact flow (`flow_net_config`), then the
global-local model on its flow, the network fixed or fine-tuned with the sparse depth
loss, and the network with a (32, 16, 1) conv head trained by the sparse loss alone;
beside them the same model on the stored DIS flow. Every run of the flow experiment
trains at the lower rate of the learning-rate check (fine-tuning the flow network at
the CPU suite's 1e-3 collapsed) and without the epipolar term, the teacher and the
refinement (they read the stored flow).

`run_config` turns a run into its `gld.runs.config.TrainConfig`; `gld.paper.runner` trains,
reuses and scores them.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any

import numpy as np

from gld.runs import config, flow_config

# The main job's recipe for the global-local model (experiments/flags/demo.flags): its
# architecture, and the loss weights by which its global module learns the motion.
MAIN_RECIPE = {"encoder_norm": "instance", "use_image_pair": False, "pose_refinement_steps": 10}
MAIN_MOTION_WEIGHTS = {"epipolar_weight": 0.1, "pose_teacher_weight": 1.0}
# The recipe for a model without an encoder's pose to refine, or without the flow.
MAIN_RECIPE_WITHOUT_MOTION = {**MAIN_RECIPE, "pose_refinement_steps": 0}
# The depth models that run the learned flow network (and start from the suite's).
FLOW_NET_MODELS = ("global_local_flow_net", "flow_net_head")

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
    # The paper's main experiments in about 3 hours on the 2-core CPU machine at 128x96
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
        hours="about 3 hours on 2 CPU cores (DispNet: 5.7 s a step, FCRN: 4.8 s)",
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


@dataclasses.dataclass(frozen=True)
class Run:
    """One training run of a suite.

    Attributes:
      name: its workdir's name under <suite workdir>/runs/, and its key in the report.
      model: a name of `gld.models.registry.MODELS`.
      label: how tables name it.
      varying: trained and tested on the varying-intrinsics dataset.
      options: TrainConfig fields it sets beyond the suite's (gt_pixels, flow_source, ...).
      model_config: the model's constructor options.
      curve: evaluated over training (the over-fitting figure).
      rate_of: the main-table run whose learning-rate check sets this run's peak rate
        (`with_compared_rate`); None: the suite's rate, or its own options'.
    """

    name: str
    model: str
    label: str
    varying: bool = False
    options: dict[str, Any] = dataclasses.field(default_factory=dict)
    model_config: dict[str, Any] = dataclasses.field(default_factory=dict)
    curve: bool = False
    rate_of: str | None = None


def low_rate_name(name: str) -> str:
    """The learning-rate check's run of a main-table run."""
    return f"{name}_low_lr"


RATE_CHECKED = (
    "global_local_1px",
    "small_encdec_1px",
    "eigen_1px",
    "dispnet_1px",
    "fcrn_1px",
    "struct2depth",
    "struct2depth_flow",
)
# The flow experiment's runs: the model on the stored DIS flow, then on the network's.
FLOW_EXPERIMENT = ("flow_dis", "flow_net_fixed", "flow_net_finetuned", "flow_net_head")


# The runs trained with one fixed supervised pixel per image, by model.
FIXED_PIXEL_RUNS = {
    "global_local": "global_local_1px_fixed",
    "small_encdec": "small_encdec_1px_fixed",
}


def density_name(gt_pixels: int) -> str:
    """ "1px", "4px", ... or "dense" (gt_pixels 0)."""
    return "dense" if gt_pixels == 0 else f"{gt_pixels}px"


def _global_local(name: str, label: str, *, motion: bool = True, **kwargs) -> Run:
    """A global-local run of the main recipe; `motion=False` drops what teaches g the
    motion (the epipolar term, the pose teacher, the refinement)."""
    recipe = MAIN_RECIPE if motion else MAIN_RECIPE_WITHOUT_MOTION
    model_config = {**recipe, **kwargs.pop("model_config", {})}
    options = {key: value if motion else 0.0 for key, value in MAIN_MOTION_WEIGHTS.items()}
    options.update(kwargs.pop("options", {}))
    return Run(name, "global_local", label, options=options, model_config=model_config, **kwargs)


BASELINE_LABELS = {
    "small_encdec": "Small Enc-Dec",
    "eigen": "Eigen",
    "dispnet": "DispNet",
    "fcrn": "FCRN",
}


def suite_runs(scale: Scale) -> list[Run]:
    """Every training run of a suite, in the order they are made: the main table first
    (its learning-rate check, then the large baselines' rows), then the ablations, the
    densities, the true flow and pose given, the varying intrinsics, and the paper's
    remaining comparisons."""
    runs = [_global_local("global_local_1px", "global-local", curve=True)]
    runs += [
        Run("small_encdec_1px", "small_encdec", "Small Enc-Dec"),
        Run("eigen_1px", "eigen", "Eigen"),
    ]
    runs += _rate_checks(scale, runs)
    large = [
        Run("dispnet_1px", "dispnet", "DispNet", curve=True),
        Run("fcrn_1px", "fcrn", "FCRN", curve=True),
    ]
    runs += large + _rate_checks(scale, large)
    runs += [
        _global_local(
            "global_local_image_pair",
            "+ image pair (the paper's global module input)",
            model_config={"use_image_pair": True},
        ),
        _global_local(
            "global_local_no_coordconv", "- CoordConv", model_config={"use_coordinates": False}
        ),
        _global_local(
            "global_local_no_global_module",
            "- global module (static filters; no epipolar term, teacher or refinement)",
            motion=False,
            model_config={"use_global_module": False},
        ),
        _global_local(
            "global_local_no_flow",
            "- flow (the image pair instead; no epipolar term, teacher or refinement)",
            motion=False,
            model_config={"use_flow": False},
        ),
        _global_local(
            "global_local_no_epipolar",
            "- epipolar term, teacher and refinement (g from the depth loss alone)",
            motion=False,
        ),
    ]
    for gt_pixels in DENSITIES[1:]:
        suffix = density_name(gt_pixels)
        runs.append(
            _global_local(
                f"global_local_{suffix}",
                f"global-local, {suffix}",
                options={"gt_pixels": gt_pixels},
                rate_of="global_local_1px",
            )
        )
        runs.append(
            Run(
                f"small_encdec_{suffix}",
                "small_encdec",
                f"Small Enc-Dec, {suffix}",
                options={"gt_pixels": gt_pixels},
                rate_of="small_encdec_1px",
            )
        )
        if gt_pixels in scale.large_densities:
            runs.append(
                Run(
                    f"dispnet_{suffix}",
                    "dispnet",
                    f"DispNet, {suffix}",
                    options={"gt_pixels": gt_pixels},
                    rate_of="dispnet_1px",
                )
            )
    # One pixel per image that stays the same every epoch, as a robot's range sensor
    # gives it (the runs above draw a training image's pixels again each epoch).
    fixed_pixel = [
        _global_local(
            FIXED_PIXEL_RUNS["global_local"],
            "global-local, one fixed pixel",
            options={"gt_pixels": 1, "fixed_sparse_pixels": True},
            rate_of="global_local_1px",
        ),
        Run(
            FIXED_PIXEL_RUNS["small_encdec"],
            "small_encdec",
            "Small Enc-Dec, one fixed pixel",
            options={"gt_pixels": 1, "fixed_sparse_pixels": True},
            rate_of="small_encdec_1px",
        ),
    ]
    runs += fixed_pixel if scale.further else []
    runs += [
        _global_local(
            "global_local_gt_flow", "global-local, true flow", options={"flow_source": "gt"}
        ),
        _global_local(
            "global_local_gt_pose",
            "global-local, true pose given (Ours-GT Pose)",
            motion=False,
            model_config={"global_source": "pose"},
        ),
        _global_local(
            "global_local_flow_pose",
            "global-local, its flow's essential-matrix pose given",
            motion=False,
            model_config={"global_source": "flow_pose"},
        ),
    ]
    runs += [
        _global_local(
            "global_local_varying", "global-local", varying=True, rate_of="global_local_1px"
        ),
        Run(
            "small_encdec_varying",
            "small_encdec",
            "Small Enc-Dec",
            varying=True,
            rate_of="small_encdec_1px",
        ),
        Run("eigen_varying", "eigen", "Eigen", varying=True, rate_of="eigen_1px"),
    ]
    if scale.large_densities == DENSITIES:  # the paper's scale: DispNet too
        runs.append(
            Run("dispnet_varying", "dispnet", "DispNet", varying=True, rate_of="dispnet_1px")
        )
    if not scale.further:
        return runs
    # The paper's remaining comparisons: the self-supervised baseline, the flow experiment.
    self_supervised = [
        Run("struct2depth", "struct2depth", "Struct2Depth (self-supervised)"),
        Run("struct2depth_flow", "struct2depth_flow", "Struct2Depth + Flow (self-supervised)"),
    ]
    runs += self_supervised + _rate_checks(scale, self_supervised)
    rate = {"learning_rate": scale.check_learning_rate or scale.learning_rate}
    runs += [
        _global_local("flow_dis", "global-local, DIS flow (stored)", motion=False, options=rate),
        *(
            Run(
                f"flow_net_{state}",
                "global_local_flow_net",
                f"global-local, flow network {label}",
                options=rate,
                model_config={
                    "global_local": MAIN_RECIPE_WITHOUT_MOTION,
                    "flow_trainable": trainable,
                },
            )
            for state, label, trainable in (
                ("fixed", "fixed", False),
                ("finetuned", "fine-tuned", True),
            )
        ),
        Run("flow_net_head", "flow_net_head", "flow network + (32, 16, 1) head", options=rate),
    ]
    return runs


def _rate_checks(scale: Scale, runs: list[Run]) -> list[Run]:
    """The learning-rate check's runs of those of `runs` in `RATE_CHECKED`."""
    if scale.check_learning_rate is None:
        return []
    return [
        dataclasses.replace(
            run,
            name=low_rate_name(run.name),
            label=f"{run.label}, peak rate {scale.check_learning_rate:g}",
            options={**run.options, "learning_rate": scale.check_learning_rate},
        )
        for run in runs
        if run.name in RATE_CHECKED
    ]


# Training losses a run logs at least (one every 50 steps, more often in a shorter run):
# the learning-rate check averages the last quarter of them, so a 150-step run is
# compared on a dozen batches, not one.
TRAINING_RECORDS = 40


def training_loss(result: dict) -> float | None:
    """A run's mean loss on its supervised training pixels (a self-supervised run's: its
    photometric loss) over the last quarter of its logged steps (what the learning-rate
    check compares; never the test split)."""
    curves = result["curves"]
    values = [value for _, value in curves["train"] or curves.get("loss", [])]
    if not values:
        return None
    return float(np.mean(values[-max(1, len(values) // 4) :]))


# A logged gradient norm below this fraction of the run's largest one has vanished. On
# the cpu_full suite the learning runs keep a quarter of their records above 1e-2 of their
# largest norm (FCRN the lowest, at 1e-2); a self-supervised run with every pixel out of
# view sits at 3e-4 to 5e-4 of it, with a rare record of 5e-2 when a batch lands a
# pixel back in view, and a saturated output at 0.
VANISHED_GRADIENT = 1e-3


def collapse(result: dict) -> tuple[int, int, int] | None:
    """(first step, count, logged steps) of the vanished gradients of a run that
    collapsed: its gradient norm is below `VANISHED_GRADIENT` of its largest logged one
    at a quarter or more of its logged steps (a saturated output no longer learns). The
    first step is the first whose norm has vanished against the largest one logged up to
    it (an early step of a run whose gradient spiked later is small against the spike,
    not vanished). None otherwise, or without a logged gradient."""
    norms = result["curves"].get("grad_norm", [])
    if not norms:
        return None
    so_far = np.maximum.accumulate([norm for _, norm in norms])
    vanished = [step for step, norm in norms if norm <= VANISHED_GRADIENT * so_far[-1]]
    if 4 * len(vanished) < len(norms):
        return None
    first = next(
        step
        for (step, norm), top in zip(norms, so_far, strict=True)
        if norm <= VANISHED_GRADIENT * top
    )
    return int(first), len(vanished), len(norms)


def compared_run(scale: Scale, name: str, result_of: Callable[[str], dict | None]) -> str | None:
    """The run of a main-table model that the comparisons use: with a learning-rate
    check, the one of its two rates with the lower training loss, unless that one
    collapsed and the other did not (a collapsed self-supervised run can have the lower
    photometric loss); None until both have finished. Else the run itself. `result_of`
    gives a run's result by its name."""
    candidates = rate_runs(scale, name)
    if len(candidates) == 1:
        return name
    results = [result_of(n) for n in candidates]
    if None in results:
        return None
    losses = [training_loss(r) for r in results]
    if None in losses:
        return None
    collapsed = [collapse(r) is not None for r in results]
    if collapsed.count(True) == 1:
        return candidates[collapsed.index(False)]
    return candidates[int(np.argmin(losses))]


def with_compared_rate(
    scale: Scale, run: Run, result_of: Callable[[str], dict | None]
) -> Run | None:
    """`run` at the peak rate its model's learning-rate check chose (`Run.rate_of`:
    the rate of `compared_run`), so a density's or the varying intrinsics' run of a model
    trains at the rate its main-table row is compared at; None until that check has
    finished. A run without `rate_of` is returned as it is."""
    if run.rate_of is None:
        return run
    compared = compared_run(scale, run.rate_of, result_of)
    if compared is None:
        return None
    low = compared != run.rate_of
    rate = scale.check_learning_rate if low else scale.learning_rate
    return dataclasses.replace(run, options={**run.options, "learning_rate": rate})


def rate_runs(scale: Scale, name: str) -> list[str]:
    """The runs a model's comparisons may use: both rates of a checked model."""
    if scale.check_learning_rate is None or name not in RATE_CHECKED:
        return [name]
    return [name, low_rate_name(name)]


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
