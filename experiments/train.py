r"""Trains a depth model and evaluates it: `python -m experiments.train [--flagfile=...]`.

With no flags this is the demo: it builds the embedded benchmark `gld_scenes/small` on
first use, trains the global-local model with ONE supervised pixel per image, evaluates
it and the dataset-mean baseline on the test split and leaves everything in runs/demo.
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
# warm-up and cosine decay; WORKSPACE.md). Paper flagfiles set Adam 1e-4, constant.
common.define_training_flags(
    steps=2000, eval_every=1000, learning_rate=1e-3, lr_schedule="cosine", warmup_steps=100
)
common.define_architecture_flags()
common.define_data_flags()
common.define_distributed_flags()


def main(argv):
    del argv
    common.initialise()
    from gld import config, train

    builder = common.prepare_dataset()
    height, width = common.dataset_resolution(builder)
    run_config = config.TrainConfig(
        model_config=common.architecture_options() if FLAGS.model == "global_local" else {},
        dataset=FLAGS.dataset,
        height=height,
        width=width,
        **common.training_options(),
    )
    common.write_flags(FLAGS.workdir)
    print(
        f"dataset {FLAGS.dataset}: {builder.info.splits['train'].num_examples} train / "
        f"{builder.info.splits['test'].num_examples} test pairs at {width}x{height}"
    )
    train.train_and_evaluate(
        run_config,
        FLAGS.workdir,
        common.data_source(builder, "train"),
        common.data_source(builder, "test"),
    )
    if FLAGS.final_eval:
        from gld import evaluation

        evaluation.evaluate_workdir(
            FLAGS.workdir,
            common.data_source(builder, "test"),
            train_source=common.data_source(builder, "train"),
            dataset=builder.info.full_name,
            height=height,
            width=width,
            num_figures=FLAGS.num_figures,
        )


if __name__ == "__main__":
    app.run(main)
