r"""Compares depth methods on one dataset: `python -m experiments.compare [--flagfile=...]`.

    python -m experiments.compare --dataset=gld_scenes/small --workdir=runs/compare_small \
        --gt_pixels=1 --steps=2500 [--models=global_local,dispnet] [--classical=sfm_flow]

Trains every selected learned model (`--models`, gld.models.registry.MODELS) with the same
budget, seed, loss, optimiser and input pipeline in <workdir>/<model> (a finished run
is reused, an unfinished one resumed), evaluates them and the classical baselines
(`--classical`, gld.models.baselines.CLASSICAL, no training) on the same split with the same
flow, and writes <workdir>/compare/:
  table.md      rows = methods; Abs-Inv, Abs-Rel, S-RMSE as mean ± std over examples,
                Abs-Inv as a multiple of the dataset mean's, the protocol stamp, and each
                method's parameters, training and failures;
  results.json  the same numbers (every per-example metric's mean, std and count).
The references, the dataset mean, the per-pair oracle constant (which sees the truth)
and sfm_flow (the classical pipeline on the same flow: essential matrix + triangulation,
no training), are in every comparison, listed in `--classical` or not.

Every method is scored as `python -m experiments.evaluate` scores it: a demon/* dataset by
DeMoN's protocol by default (--truth_resolution=file), against the depth of the files its
split was built from (in --manual_dir, else where the build found them), each prediction
resized to it by nearest neighbour. Without those files the comparison is refused before
anything is trained: give --manual_dir, or --truth_resolution=record to score at the
records' resolution, which is not DeMoN's protocol. The stamp names the resolution and the
records' protocol.
"""

from __future__ import annotations

from pathlib import Path

from absl import app, flags

from experiments import common
from gld import files

FLAGS = flags.FLAGS

LEARNED_DEFAULT = ["global_local", "eigen", "dispnet", "fcrn", "small_encdec"]
CLASSICAL_DEFAULT = ["dataset_mean", "oracle_pair_median", "triangulation_gt_pose", "sfm_flow"]

flags.DEFINE_string("workdir", "runs/compare", "Holds one run per model and compare/.")
flags.DEFINE_list("models", LEARNED_DEFAULT, "Learned models to train and compare.")
flags.DEFINE_list(
    "classical", CLASSICAL_DEFAULT, "Classical baselines to compare (the references always)."
)
common.define_training_flags(exclude=("model",), steps=2500, eval_every=0)
flags.DEFINE_string("split", "test", "Split every method is evaluated on.")
flags.DEFINE_integer("max_examples", 0, "Evaluate the first N examples only (0 = all).")
common.define_truth_resolution_flag()
common.define_data_flags()
common.define_flow_net_flags()


def main(argv):
    del argv
    common.initialise()
    from data.demon import file_truth
    from gld.analysis import comparison
    from gld.evaluation import evaluation_run
    from gld.models import registry
    from gld.models.baselines import CLASSICAL

    for flag, names, valid in (
        ("models", FLAGS.models, registry.MODELS),
        ("classical", FLAGS.classical, CLASSICAL),
    ):
        unknown = sorted(set(names) - set(valid))
        if unknown:
            raise app.UsageError(f"--{flag}: unknown {unknown}; valid: {sorted(valid)}")
    model_configs = {name: common.flow_net_options(name) for name in FLAGS.models}
    for name in FLAGS.models:  # every run's options, before anything is built or trained
        common.train_config(model=name, model_config=model_configs[name])
    builder = common.prepare_dataset()
    height, width = common.dataset_resolution(builder)
    eval_source = common.data_source(builder, FLAGS.split)
    # The truth is opened and checked before anything is trained.
    truth, _ = evaluation_run.open_truth(
        builder,
        FLAGS.split,
        eval_source,
        open_file_truth=file_truth.for_split,
        truth_resolution=FLAGS.truth_resolution,
        manual_dir=FLAGS.manual_dir,
        max_examples=FLAGS.max_examples,
    )
    try:
        comparison.run_comparison(
            workdir=FLAGS.workdir,
            dataset=builder.info.full_name,
            train_source=common.data_source(builder, "train"),
            eval_source=eval_source,
            height=height,
            width=width,
            models=FLAGS.models,
            classical_methods=FLAGS.classical,
            train_config=common.training_options(),
            split=FLAGS.split,
            eval_batch_size=FLAGS.eval_batch_size,
            max_examples=FLAGS.max_examples,
            model_configs=model_configs,
            truth=truth,
            records_protocol=evaluation_run.records_protocol(builder, FLAGS.split),
        )
    finally:
        if truth is not None:
            truth.close()
    # Next to the table it produced: the flags that made it (a valid --flagfile).
    files.write_atomically(Path(FLAGS.workdir) / "compare" / "flags.txt", common.flags_file_text())


if __name__ == "__main__":
    common.run(main)
