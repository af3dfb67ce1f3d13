r"""Evaluates a trained workdir, a classical baseline or another system's stored depth maps
on a whole split.

    python -m experiments.evaluate --workdir=runs/demo
    python -m experiments.evaluate --method=triangulation_gt_pose --dataset=gld_scenes/small \
        --workdir=runs/triangulation [--flow_source=gt]
    python -m experiments.evaluate --predictions=out/other_system --dataset=demon/sun3d \
        --manual_dir=~/demon --workdir=runs/other_system [--predictions_scale=raw]
    python -m experiments.evaluate --workdir=runs/sun3d --manual_dir=~/demon
    python -m experiments.evaluate --workdir=runs/sun3d --truth_resolution=record

--predictions reads one file per example id, the id's "/" replaced by "__": a 2-D float
`.npy` of depth or a 16-bit PNG (value x --png_depth_scale = depth); a map at another
resolution is resized by nearest neighbour (details: `gld.evaluation.stored_predictions`). A missing
or bad file stops the run, naming it, before anything is written.

A demon/* dataset is scored by DeMoN's protocol by default (--truth_resolution=file):
every method against the ground truth at the resolution of DeMoN's files (640x480 for
SUN3D and RGB-D), read by example id from the files the split was built from (in
--manual_dir, else where the build found them, if they are still there and unchanged),
each prediction resized to it by nearest neighbour, as DeMoN's evaluation does
(`data.demon.file_truth`), in DeMoN's order (the records' order; --max_examples takes
DeMoN's first pairs). Without those files the run is refused: give --manual_dir, or
--truth_resolution=record to score at the records' resolution, which is not DeMoN's
protocol. Other datasets are scored at the records' resolution (record). The table's
stamp names the resolution and the records' protocol (WebP decoder, depth resampling,
order).

Writes <workdir>/eval/ for the workdir's own evaluation (latest checkpoint, whole test
split, its flow and dataset), else <workdir>/eval_<what differs>/ (e.g. eval_train_first2,
eval_step500, eval_flow-gt, eval_truth-file), so one evaluation never replaces another;
a folder holding an evaluation of something else is refused. Each holds metrics.json,
table.md (mean ± std per metric, Abs-Inv as a multiple of the dataset mean's, protocol
stamp), per_example_<method>.csv and figures/ (image 1, ground truth, prediction,
error, the supervised pixel circled; one colour scale for all). The references (the
dataset mean, the per-pair oracle constant, which sees the truth, and sfm_flow, the
classical pipeline: pose from the essential matrix of the flow, then triangulation, no
training) are evaluated alongside on the same examples with the same flow; --nodataset_mean,
--nooracle and --nosfm_flow leave one out. A folder holding the same evaluation is
rewritten with this run's rows.
"""

from __future__ import annotations

from pathlib import Path

from absl import app, flags

from experiments import common
from gld.evaluation import stored_predictions
from gld.models.baselines import CLASSICAL

FLAGS = flags.FLAGS

flags.DEFINE_string("workdir", "runs/demo", "Run directory; results go to <workdir>/eval*.")
flags.DEFINE_enum(
    "method",
    None,
    sorted(CLASSICAL),
    "A classical method (no training) instead of the workdir's model.",
)
flags.DEFINE_string(
    "predictions",
    None,
    "A folder of depth maps another system wrote, one per example id (see the module "
    "docstring), scored instead of the workdir's model.",
)
flags.DEFINE_enum(
    "predictions_scale",
    stored_predictions.DEFAULT_DEPTH_SCALE,
    list(stored_predictions.DEPTH_SCALES),
    "Scale of --predictions: normalised (the pair's translation has norm 1, as gld and "
    "DeMoN predict) or raw (the dataset's depth units, e.g. metres; divided by each "
    "pair's ||t|| as the ground truth is).",
)
flags.DEFINE_float(
    "png_depth_scale",
    stored_predictions.DEFAULT_PNG_DEPTH_SCALE,
    "Depth per unit of a 16-bit PNG prediction (0.001: millimetres to metres); 0 means no "
    "prediction (the pixel is excluded and counted).",
)
common.define_truth_resolution_flag()
flags.DEFINE_string("split", "test", "Split to evaluate.")
flags.DEFINE_integer("batch_size", 16, "Evaluation batch size (last batch padded).")
flags.DEFINE_integer("num_figures", 8, "Example figures to draw.")
flags.DEFINE_integer("max_examples", 0, "Evaluate the first N examples only (0 = all).")
flags.DEFINE_bool("dataset_mean", True, "Also evaluate the dataset-mean baseline.")
flags.DEFINE_bool(
    "oracle", True, "Also evaluate the per-pair oracle constant (each pair's median truth)."
)
flags.DEFINE_bool(
    "sfm_flow",
    True,
    "Also evaluate the classical pipeline on the same flow (essential matrix + "
    "triangulation, no training).",
)
flags.DEFINE_integer("step", None, "Checkpoint step to evaluate (default: latest).")
common.define_compile_cache_flag(
    "where the training launch kept them (a workdir without compile_cache/ gets none)."
)
common.define_data_flags(default_dataset=None)
common.define_flow_source_flag()
common.define_distributed_flags()


def main(argv):
    del argv
    common.initialise()
    from data.demon import file_truth
    from gld.evaluation import evaluation_run
    from gld.runs import workdir as workdir_lib

    if FLAGS.compile_cache and (Path(FLAGS.workdir) / workdir_lib.COMPILE_CACHE_DIR).is_dir():
        workdir_lib.keep_compiled_programs(FLAGS.workdir)

    if FLAGS.method and FLAGS.predictions:
        raise app.UsageError("give --method or --predictions, not both")
    predictions = None
    if FLAGS.predictions:
        predictions = stored_predictions.StoredPredictions(
            FLAGS.predictions,
            depth_scale=FLAGS.predictions_scale,
            png_depth_scale=FLAGS.png_depth_scale,
        )
    evaluation_run.evaluate_split(
        FLAGS.workdir,
        prepare_dataset=common.prepare_dataset,
        open_file_truth=file_truth.for_split,
        dataset=FLAGS.dataset,
        method=FLAGS.method,
        predictions=predictions,
        truth_resolution=FLAGS.truth_resolution,
        manual_dir=FLAGS.manual_dir,
        split=FLAGS.split,
        batch_size=FLAGS.batch_size,
        num_figures=FLAGS.num_figures,
        max_examples=FLAGS.max_examples,
        with_dataset_mean=FLAGS.dataset_mean,
        with_oracle=FLAGS.oracle,
        with_sfm_flow=FLAGS.sfm_flow,
        step=FLAGS.step,
        flow_source=FLAGS.flow_source,
    )


if __name__ == "__main__":
    common.run(main)
