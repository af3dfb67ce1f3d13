r"""Trains a depth model and evaluates it: `python -m experiments.train [--flagfile=...]`.

With no flags this is the demo: it builds the embedded benchmark `gld_scenes/small` on
first use, trains the global-local model with ONE supervised pixel per image, evaluates
it with its references (the dataset mean, the per-pair oracle constant and sfm_flow, the
classical pipeline on the same flow) on the test split, prints the table and leaves
everything in runs/demo.
Re-running the same command resumes from the last checkpoint.
"""

from __future__ import annotations

from absl import app, flags

from experiments import common

FLAGS = flags.FLAGS

flags.DEFINE_string("workdir", "runs/demo", "Run directory (checkpoints, logs, eval).")
flags.DEFINE_bool("final_eval", True, "Evaluate the final model on the whole test split.")
flags.DEFINE_integer("num_figures", 8, "Example figures written by the final evaluation.")
# The main job's recipe: the best measured within its CPU budget (Adam 1e-3, warm-up and
# cosine decay; an instance-normalised global encoder that sees the flow alone, whose
# pose is taught by the epipolar term at 0.1 and the classical pose teacher and refined
# on the flow; WORKSPACE.md), written once in gld.paper.suite. Paper flagfiles set Adam
# 1e-4, constant, none of the motion terms, and the paper's global module (no
# normalisation, the image pair and the flow).
from gld.paper.suite import MAIN_MOTION_WEIGHTS, MAIN_RECIPE  # noqa: E402

common.define_training_flags(
    steps=2000,
    eval_every=1000,
    learning_rate=1e-3,
    lr_schedule="cosine",
    warmup_steps=100,
    **MAIN_MOTION_WEIGHTS,
)
common.define_architecture_flags(**MAIN_RECIPE)
common.define_flow_net_flags()
common.define_data_flags()
common.define_distributed_flags()


def _with_stored_architecture(model_config: dict) -> dict:
    """A relaunch of a workdir keeps its run's architecture: an option the command line
    does not give takes the stored value, not this launcher's default (which may have
    changed since the run began)."""
    from gld.models import registry
    from gld.runs import workdir as workdir_lib

    stored = workdir_lib.stored_architecture(FLAGS.workdir)
    if FLAGS.model != "global_local" or not stored or stored.get("model") != FLAGS.model:
        return model_config
    kept = {
        name: stored[name]
        for name in registry.architecture_options()
        if not FLAGS[name].present
        and stored.get(name) is not None
        and stored[name] != model_config.get(name)
    }
    if kept:
        listed = ", ".join(f"{name}={value}" for name, value in sorted(kept.items()))
        print(f"{FLAGS.workdir} was trained with {listed}: kept (flags given override)")
    return {**model_config, **kept}


def _motion_where_it_applies(model_config: dict) -> tuple[dict, dict]:
    """The main job's ways of teaching g the motion are defaults of the global-local
    model whose encoder infers a pose: a model without one (another model, a given pose,
    no global module) trains without the epipolar term and the teacher, and one without
    it or without the flow without refinement, unless the command line asks for them."""
    from gld.runs import config

    infers_pose = config.infers_pose(FLAGS.model, model_config)
    weights = {
        name: FLAGS[name].value if infers_pose or FLAGS[name].present else 0.0
        for name in MAIN_MOTION_WEIGHTS
    }
    refines = config.refines_pose(FLAGS.model, model_config)
    if FLAGS.model == "global_local" and not refines and not FLAGS["pose_refinement_steps"].present:
        model_config = {**model_config, "pose_refinement_steps": 0}
    return model_config, weights


def main(argv):
    del argv
    common.initialise()
    import dataclasses

    from gld.training import trainer as train

    model_config = _with_stored_architecture(common.model_options(FLAGS.model))
    model_config, weights = _motion_where_it_applies(model_config)
    # Every option is checked before the dataset is built or the workdir touched.
    run_config = common.train_config(model_config=model_config, dataset=FLAGS.dataset, **weights)
    evaluates = FLAGS.final_eval or run_config.eval_every > 0
    builder, height, width, train_source, test_source = common.training_data(evaluates)
    run_config = dataclasses.replace(run_config, height=height, width=width)
    train.train_and_evaluate(
        run_config,
        FLAGS.workdir,
        train_source,
        test_source,
        records={"flags.txt": common.flags_file_text()},
    )
    if FLAGS.final_eval:
        from gld.evaluation import trained_run

        trained_run.evaluate_workdir(
            FLAGS.workdir,
            test_source,
            train_source=train_source,
            dataset=builder.info.full_name,
            height=height,
            width=width,
            num_figures=FLAGS.num_figures,
            batch_size=run_config.eval_batch_size,
        )


if __name__ == "__main__":
    app.run(main)
