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
# The main job's recipe: the best measured within its 15-minute CPU budget (Adam 1e-3,
# warm-up and cosine decay, the epipolar term at 0.1, an instance-normalised global
# encoder that sees the flow alone; WORKSPACE.md). Paper flagfiles set Adam 1e-4,
# constant, no epipolar term, and the paper's global module (no normalisation, the image
# pair and the flow).
MAIN_JOB_EPIPOLAR_WEIGHT = 0.1
MAIN_JOB_ARCHITECTURE = {"encoder_norm": "instance", "use_image_pair": False}
common.define_training_flags(
    steps=2000,
    eval_every=1000,
    learning_rate=1e-3,
    lr_schedule="cosine",
    warmup_steps=100,
    epipolar_weight=MAIN_JOB_EPIPOLAR_WEIGHT,
)
common.define_architecture_flags(**MAIN_JOB_ARCHITECTURE)
common.define_flow_net_flags()
common.define_data_flags()
common.define_distributed_flags()


def _with_stored_architecture(model_config: dict) -> dict:
    """A relaunch of a workdir keeps its run's architecture: an option the command line
    does not give takes the stored value, not this launcher's default (which may have
    changed since the run began)."""
    from gld import model
    from gld import workdir as workdir_lib

    stored = workdir_lib.stored_architecture(FLAGS.workdir)
    if FLAGS.model != "global_local" or not stored or stored.get("model") != FLAGS.model:
        return model_config
    kept = {
        name: stored[name]
        for name in model.architecture_options()
        if not FLAGS[name].present
        and stored.get(name) is not None
        and stored[name] != model_config.get(name)
    }
    if kept:
        listed = ", ".join(f"{name}={value}" for name, value in sorted(kept.items()))
        print(f"{FLAGS.workdir} was trained with {listed}: kept (flags given override)")
    return {**model_config, **kept}


def main(argv):
    del argv
    common.initialise()
    import dataclasses

    from gld import config, train

    model_config = _with_stored_architecture(common.model_options(FLAGS.model))
    # The default epipolar weight is the global-local model's; a model whose global
    # parameters cannot stand for a pose trains without the term unless it is asked for.
    epipolar_weight = FLAGS.epipolar_weight
    if not FLAGS["epipolar_weight"].present and not config.infers_pose(FLAGS.model, model_config):
        epipolar_weight = 0.0
    # Every option is checked before the dataset is built or the workdir touched.
    run_config = common.train_config(
        model_config=model_config, dataset=FLAGS.dataset, epipolar_weight=epipolar_weight
    )
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
        from gld import evaluation

        evaluation.evaluate_workdir(
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
