"""The suites' runs: one recipe and budget for every learned model, the ablations'
switches, the densities, and the rate each run trains at."""

import dataclasses

import pytest

from gld.paper import suite as paper_suite
from gld.paper.rate_check import RATE_CHECKED, TRAINING_RECORDS, low_rate_name
from gld.paper.run_configs import flow_net_config, run_config
from gld.paper.scales import SUITES
from gld.runs import recipe


def test_the_ablations_change_one_switch_of_the_main_recipe():
    scale = SUITES["cpu"]
    configs = {
        run.name: run_config(scale, run, height=96, width=128)
        for run in paper_suite.suite_runs(scale)
        if run.model == "global_local"
    }
    main = configs["global_local_1px"]
    assert main.model_config == {
        "encoder_norm": "instance",
        "use_image_pair": False,
        "pose_refinement_steps": 15,
        "pose_refinement_starts": 5,
        "border": "edge",
        "derotate_flow": True,
        "parallax_depth": True,
    }
    assert main.epipolar_weight == 0.1 and main.pose_teacher_weight == 1.0
    assert main.gt_pixels == 1 and main.flow_source == "estimated"
    # The over-fitting figure needs the main run's test curve.
    assert main.eval_every == scale.steps // scale.curve_evaluations

    def differences(name):
        config = configs[name]
        changed = {k: v for k, v in config.model_config.items() if main.model_config.get(k) != v}
        options = ("epipolar_weight", "pose_teacher_weight", "gt_pixels", "flow_source", "dataset")
        for option in options:
            if getattr(config, option) != getattr(main, option):
                changed[option] = getattr(config, option)
        return changed

    assert differences("global_local_image_pair") == {"use_image_pair": True}
    assert differences("global_local_no_coordconv") == {"use_coordinates": False}
    # Without g from the encoder, or without the flow, nothing teaches g the motion.
    no_encoder_pose = {
        "epipolar_weight": 0.0,
        "pose_teacher_weight": 0.0,
        "pose_refinement_steps": 0,
        "pose_refinement_starts": 1,
    }
    no_motion = {**no_encoder_pose, "derotate_flow": False, "parallax_depth": False}
    assert differences("global_local_no_global_module") == {"use_global_module": False, **no_motion}
    assert differences("global_local_no_flow") == {"use_flow": False, **no_motion}
    assert differences("global_local_no_epipolar") == no_motion
    assert differences("global_local_gt_flow") == {"flow_source": "gt"}
    # A given pose is read against the flow as the encoder's is.
    assert differences("global_local_gt_pose") == {"global_source": "pose", **no_encoder_pose}
    assert differences("global_local_flow_pose") == {
        "global_source": "flow_pose",
        **no_encoder_pose,
    }
    assert differences("global_local_varying") == {"dataset": "gld_scenes/small_varying"}
    for gt_pixels in (4, 16, 64, 0):
        name = f"global_local_{paper_suite.density_name(gt_pixels)}"
        assert differences(name) == {"gt_pixels": gt_pixels}


def test_densities_and_the_large_models_budget():
    cpu = {run.name: run for run in paper_suite.suite_runs(SUITES["cpu"])}
    paper = {run.name: run for run in paper_suite.suite_runs(SUITES["paper"])}
    for model in ("global_local", "small_encdec"):
        for suffix in ("1px", "4px", "16px", "64px", "dense"):
            assert f"{model}_{suffix}" in cpu and f"{model}_{suffix}" in paper
    # DispNet: every density at the paper's scale, one pixel and dense on the CPU (one
    # pixel at both rates of the learning-rate check, as every main-table model).
    assert {n for n in cpu if n.startswith("dispnet")} == {
        "dispnet_1px",
        "dispnet_1px_low_lr",
        "dispnet_dense",
    }
    assert {n for n in paper if n.startswith("dispnet")} == {
        "dispnet_1px",
        "dispnet_1px_low_lr",
        "dispnet_4px",
        "dispnet_16px",
        "dispnet_64px",
        "dispnet_dense",
        "dispnet_varying",
    }
    assert paper_suite.density_name(0) == "dense" and paper_suite.density_name(16) == "16px"
    # The paper's scale gives every model the same budget; the CPU one cannot.
    assert SUITES["paper"].large_steps == SUITES["paper"].steps == 94_000
    assert SUITES["cpu"].large_steps < SUITES["cpu"].steps


def test_the_remaining_comparisons_self_supervised_and_the_flow_experiment():
    scale = SUITES["cpu_full"]
    runs = {run.name: run for run in paper_suite.suite_runs(scale)}

    def config(name):
        return run_config(scale, runs[name], height=96, width=128)

    assert config("struct2depth").model == "struct2depth"
    assert config("struct2depth_flow").model == "struct2depth_flow"
    assert config("struct2depth_low_lr").learning_rate == scale.check_learning_rate
    # The flow experiment: the main recipe without the motion terms, on the stored DIS
    # flow or on the network's, fixed or fine-tuned; the head; one rate for all four.
    dis = config("flow_dis")
    assert dis.model == "global_local" and dis.model_config == recipe.ARCHITECTURE_WITHOUT_MOTION
    fixed, finetuned, head = (
        config(n) for n in ("flow_net_fixed", "flow_net_finetuned", "flow_net_head")
    )
    assert fixed.model == finetuned.model == "global_local_flow_net"
    assert (
        fixed.model_config["global_local"]
        == finetuned.model_config["global_local"]
        == recipe.ARCHITECTURE_WITHOUT_MOTION
    )
    assert not fixed.model_config["flow_trainable"] and finetuned.model_config["flow_trainable"]
    assert head.model == "flow_net_head"
    for run in (dis, fixed, finetuned, head):
        assert run.epipolar_weight == 0 and run.learning_rate == scale.check_learning_rate
        assert run.pose_teacher_weight == 0
        assert (run.steps, run.gt_pixels, run.dataset) == (scale.steps, 1, scale.dataset)
    flow = flow_net_config(scale, height=96, width=128)
    assert (flow.steps, flow.batch_size, flow.warmup_steps) == (5000, 8, 100)


def test_the_cpu_suite_is_the_full_ones_main_experiments_at_half_the_budget():
    """The 3-hour suite trains the runs of the paper's main experiments that cpu_full
    trains, in the same order and with the same options but the budget; the further runs
    (one fixed pixel, the self-supervised baseline, the flow experiment) only cpu_full."""
    cpu, full = SUITES["cpu"], SUITES["cpu_full"]
    assert not cpu.further and full.further
    assert (cpu.steps, cpu.probe_steps) == (full.steps // 2, full.probe_steps // 2)
    assert cpu.large_steps < full.large_steps
    cpu_runs = paper_suite.suite_runs(cpu)
    full_runs = {run.name: run for run in paper_suite.suite_runs(full)}
    further = {
        *paper_suite.FIXED_PIXEL_RUNS.values(),
        *paper_suite.FLOW_EXPERIMENT,
        "struct2depth",
        "struct2depth_flow",
        "struct2depth_low_lr",
        "struct2depth_flow_low_lr",
    }
    assert [run.name for run in cpu_runs] == [n for n in full_runs if n not in further]
    for run in cpu_runs:
        assert run == full_runs[run.name]
        short, long = (run_config(scale, run, height=96, width=128) for scale in (cpu, full))
        differs = {k for k, v in dataclasses.asdict(short).items() if getattr(long, k) != v}
        budget = {"steps", "warmup_steps", "eval_every", "log_every", "checkpoint_every"}
        budget |= {"eval_examples"} if run.curve else set()  # its curve's test pairs
        assert differs <= budget, run.name


def test_learned_models_differ_only_where_the_suite_says():
    """Against the main run's configuration, a baseline differs in the model, its options
    and the motion terms (epipolar, pose teacher); every other option (loss weights,
    augmentation, flow, schedule, checkpoints) is the same, at the same density and dataset."""
    import dataclasses

    scale = SUITES["cpu"]
    runs = {run.name: run for run in paper_suite.suite_runs(scale)}

    def config(name):
        values = dataclasses.asdict(run_config(scale, runs[name], height=96, width=128))
        return {k: v for k, v in values.items() if k not in ("eval_every", "eval_examples")}

    main = config("global_local_1px")
    for name in ("small_encdec_1px", "eigen_1px"):
        differing = {k for k, v in config(name).items() if main[k] != v}
        assert differing == {"model", "model_config", "epipolar_weight", "pose_teacher_weight"}
    # The learning-rate check: the main table's models again, at the second rate only.
    assert {n for n in runs if n.endswith("_low_lr")} == {
        low_rate_name(n) for n in RATE_CHECKED if n in runs
    }
    for name in set(RATE_CHECKED) & set(runs):
        low = config(low_rate_name(name))
        assert {k for k, v in low.items() if config(name)[k] != v} == {"learning_rate"}
        assert low["learning_rate"] == scale.check_learning_rate < scale.learning_rate
    # The large baselines also differ in their budget (and so warm-up, checkpoints, and
    # how often they log: as many training losses for the learning-rate check).
    differing = {k for k, v in config("dispnet_1px").items() if main[k] != v}
    assert differing == {
        "model",
        "model_config",
        "epipolar_weight",
        "pose_teacher_weight",
        "steps",
        "warmup_steps",
        "checkpoint_every",
        "log_every",
    }
    for name in ("global_local_1px", "dispnet_1px"):
        records = config(name)["steps"] // config(name)["log_every"]
        assert records >= TRAINING_RECORDS, name


def test_density_and_varying_runs_train_at_their_models_compared_rate():
    scale = SUITES["cpu"]
    runs = {run.name: run for run in paper_suite.suite_runs(scale)}

    def losses(**loss):
        def result_of(name):
            if name not in loss:
                return None
            return {"curves": {"train": [[10, loss[name]]] * 8}}

        return result_of

    dense = runs["dispnet_dense"]
    assert dense.rate_of == "dispnet_1px" and runs["eigen_varying"].rate_of == "eigen_1px"
    # Until both rates of its check have finished, its rate is not known.
    assert paper_suite.with_compared_rate(scale, dense, losses(dispnet_1px=0.07)) is None
    # The lower training loss picks the rate, as for the main table.
    rated = paper_suite.with_compared_rate(
        scale, dense, losses(dispnet_1px=0.07, dispnet_1px_low_lr=0.03)
    )
    assert rated.options == {"gt_pixels": 0, "learning_rate": scale.check_learning_rate}
    rated = paper_suite.with_compared_rate(
        scale, dense, losses(dispnet_1px=0.02, dispnet_1px_low_lr=0.03)
    )
    assert rated.options["learning_rate"] == scale.learning_rate
    # The ablations keep the suite's rate.
    ablation = runs["global_local_no_coordconv"]
    assert ablation.rate_of is None
    assert paper_suite.with_compared_rate(scale, ablation, losses()) is ablation


@pytest.mark.parametrize("model", sorted(paper_suite.FIXED_PIXEL_RUNS))
def test_the_fixed_pixel_runs_keep_one_pixel_and_the_compared_rate(model):
    scale = SUITES["cpu_full"]
    runs = {run.name: run for run in paper_suite.suite_runs(scale)}
    fixed = runs[paper_suite.FIXED_PIXEL_RUNS[model]]
    config = run_config(scale, fixed, height=96, width=128)
    redrawn = run_config(scale, runs[f"{model}_1px"], height=96, width=128)
    assert (config.gt_pixels, config.fixed_sparse_pixels) == (1, True)
    assert not redrawn.fixed_sparse_pixels
    assert fixed.model == model and fixed.rate_of == f"{model}_1px"
    # Otherwise the same run: only the pixels' drawing differs (and the main run's test
    # evaluations over training, which do not change its training).
    differs = {
        key for key, value in dataclasses.asdict(config).items() if getattr(redrawn, key) != value
    }
    assert differs - {"eval_every"} == {"fixed_sparse_pixels"}
