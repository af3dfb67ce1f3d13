r"""Evaluates a trained workdir or a classical baseline on a whole split.

    python -m experiments.evaluate --workdir=runs/demo
    python -m experiments.evaluate --method=triangulation_gt_pose --dataset=gld_scenes/small \
        --workdir=runs/triangulation [--flow_source=gt]

Writes <workdir>/eval/: metrics.json, table.md (mean ± std per metric, Abs-Inv as a
multiple of the dataset mean's, protocol stamp), per_example_<method>.csv and figures/
(image 1, ground truth, prediction, error, the supervised pixel circled; one colour
scale for all). The references (the dataset mean and the per-pair oracle constant, which
sees the truth) are evaluated alongside on the same examples.
"""

from __future__ import annotations

from absl import app, flags

from experiments import common

FLAGS = flags.FLAGS

flags.DEFINE_string("workdir", "runs/demo", "Run directory; results go to <workdir>/eval.")
flags.DEFINE_string(
    "method", None, "A classical method (no training) instead of the workdir's model."
)
flags.DEFINE_string("split", "test", "Split to evaluate.")
flags.DEFINE_integer("batch_size", 16, "Evaluation batch size (last batch padded).")
flags.DEFINE_integer("num_figures", 8, "Example figures to draw.")
flags.DEFINE_integer("max_examples", 0, "Evaluate the first N examples only (0 = all).")
flags.DEFINE_bool("dataset_mean", True, "Also evaluate the dataset-mean baseline.")
flags.DEFINE_bool(
    "oracle", True, "Also evaluate the per-pair oracle constant (each pair's median truth)."
)
flags.DEFINE_integer("step", None, "Checkpoint step to evaluate (default: latest).")
common.define_data_flags(default_dataset=None)
common.define_flow_source_flag()
common.define_distributed_flags()


def main(argv):
    del argv
    common.initialise()
    from gld import evaluation
    from gld import workdir as workdir_lib

    if FLAGS.method:
        if not FLAGS.dataset:
            raise app.UsageError("--dataset is needed with --method")
        dataset = FLAGS.dataset
    else:
        config = workdir_lib.load_run_config(FLAGS.workdir)
        dataset = FLAGS.dataset or config.dataset
    builder = common.prepare_dataset(dataset)
    height, width = common.dataset_resolution(builder)
    evaluation.evaluate_workdir(
        FLAGS.workdir,
        common.data_source(builder, FLAGS.split),
        train_source=common.data_source(builder, "train"),
        dataset=builder.info.full_name,
        height=height,
        width=width,
        split=FLAGS.split,
        print_fn=print,
        num_figures=FLAGS.num_figures,
        with_dataset_mean=FLAGS.dataset_mean and FLAGS.method != "dataset_mean",
        with_oracle=FLAGS.oracle,
        batch_size=FLAGS.batch_size,
        max_examples=FLAGS.max_examples,
        step=FLAGS.step,
        classical_method=FLAGS.method,
        flow_source=FLAGS.flow_source,
    )


if __name__ == "__main__":
    app.run(main)
