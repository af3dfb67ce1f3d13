"""The paper's experimental section as one list of runs: what each suite trains and scores.

A suite (`gld.paper.scales.SUITES`) is a scale — dataset, resolution, budget — and
`suite_runs` gives its training runs: the main table's models at one pixel per image,
the ablations, the supervision densities, the given flow and given pose, and the varying
intrinsics. Every learned model of the main table is also trained at a second, lower
rate (`gld.paper.rate_check`: runs `<run>_low_lr`); the model's runs at the other
densities and on the varying intrinsics train at the rate its check chose (`Run.rate_of`,
`with_compared_rate`); the ablations, at the suite's rate (global-local's check chose it
on the CPU suite).

The global-local runs use the main job's recipe (`gld.runs.recipe`): a
global encoder with instance normalisation that sees the flow alone, and a global
module that learns the motion: the epipolar term at 0.1, the classical pose teacher
(`pose_teacher_weight`) and a search and fifteen refinement steps of the encoder's pose
on the flow (`pose_refinement_starts`, `pose_refinement_steps`), whose rotation's flow is
subtracted from the local network's flow (`derotate_flow`) and under which the flow is
triangulated for it (`parallax_depth`; a given pose, true or the essential matrix's, is
read so too). Two ablations therefore read
differently from the paper's: "+ image pair" adds the image pair the main recipe leaves
out, and the runs without a global module or without flow drop all three ways of
learning the motion too (they need g, and they read the flow); the run "- epipolar term,
teacher and refinement" measures what those cost (g learned from the depth loss
alone, as the paper's; with them go the search, the derotated flow and the triangulated
flow, which read the pose they teach). The runs given a pose have no encoder to teach
or refine.

A suite with the further runs (`Scale.further`; all but cpu) adds the control of one
fixed pixel per image to the densities, and closes with the paper's remaining
comparisons: the self-supervised baseline (Struct2Depth, with and without flow; no depth
labels) in the main table and its learning-rate check, and the flow experiment. That
one trains the learned flow network on the exact flow
(`gld.paper.run_configs.flow_net_config`), then the global-local model on its flow, the
network fixed or fine-tuned with the sparse depth loss, and the network with a
(32, 16, 1) conv head trained by the sparse loss alone; beside them the same model on
the stored DIS flow. Every run of the flow experiment trains at the lower rate of the
learning-rate check (fine-tuning the flow network at the CPU suite's 1e-3 collapsed)
and without the epipolar term, the teacher and the refinement (they read the stored
flow).

`gld.paper.run_configs` turns a run into its `gld.runs.config.TrainConfig`;
`gld.paper.runner` trains, reuses and scores them.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any

from gld.models.global_local import ABLATIONS
from gld.paper.rate_check import RATE_CHECKED, compared_run, low_rate_name
from gld.paper.scales import DENSITIES, Scale
from gld.runs import recipe

# The depth models that run the learned flow network (and start from the suite's).
FLOW_NET_MODELS = ("global_local_flow_net", "flow_net_head")


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
    architecture = recipe.ARCHITECTURE if motion else recipe.ARCHITECTURE_WITHOUT_MOTION
    model_config = {**architecture, **kwargs.pop("model_config", {})}
    options = {key: value if motion else 0.0 for key, value in recipe.MOTION_WEIGHTS.items()}
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
            "global_local_no_coordconv", "- CoordConv", model_config=ABLATIONS["no_coordconv"]
        ),
        _global_local(
            "global_local_no_global_module",
            "- global module (static filters; no epipolar term, teacher or refinement)",
            motion=False,
            model_config=ABLATIONS["no_global_module"],
        ),
        _global_local(
            "global_local_no_flow",
            "- flow (the image pair instead; no epipolar term, teacher or refinement)",
            motion=False,
            model_config=ABLATIONS["no_flow"],
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
            model_config={**recipe.ARCHITECTURE_GIVEN_POSE, "global_source": "pose"},
        ),
        _global_local(
            "global_local_flow_pose",
            "global-local, its flow's essential-matrix pose given",
            motion=False,
            model_config={**recipe.ARCHITECTURE_GIVEN_POSE, "global_source": "flow_pose"},
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
                    "global_local": recipe.ARCHITECTURE_WITHOUT_MOTION,
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
