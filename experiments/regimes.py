r"""Where a trained model beats the classical pipeline, pair by pair, and why.

    python -m experiments.regimes --workdir=runs/v2/main_s0 --output_dir=out/regimes
    python -m experiments.regimes --workdir=runs/v2/main_s0 \
        --dataset=gld_scenes/small_untextured --output_dir=out/regimes_untextured

Reads the workdir's evaluation on --dataset (default: the workdir's own; the folder
`python -m experiments.evaluate` writes, e.g. <workdir>/eval or
<workdir>/eval_gld_scenes-small_untextured, or --eval_dir): the per-pair Abs-Inv of the
model (per_example_<model>.csv) and of sfm_flow, the classical pipeline on the same flow
(per_example_sfm_flow.csv). For each evaluated pair it computes, from the dataset's
record (`gld.analysis.regimes`): the baseline (raw ||t||), the rotation share of the true flow,
the flow's end-point error, sfm_flow's pose errors (its pose estimated again from the
same flow) and, for gld_scenes, the texture kind covering most of view 1 (the pair's
scene drawn again from its seed, as the builder draws it, and checked against the
record's depth). Each property is binned in --num_bins quantile bins.

Writes to --output_dir: regimes.csv (one row per pair), regimes.md (per bin: pairs,
mean Abs-Inv of both, their ratio, the share of pairs the model wins; printed too) and
regimes.png (the per-pair ratio against each property). The dataset must be built.
"""

from __future__ import annotations

from pathlib import Path

from absl import flags

from experiments import common

FLAGS = flags.FLAGS

flags.DEFINE_string("workdir", None, "Evaluated training workdir.", required=True)
flags.DEFINE_string(
    "eval_dir",
    None,
    "The evaluation folder to read (default: the one experiments.evaluate writes for "
    "--dataset in --workdir).",
)
flags.DEFINE_string("output_dir", None, "Where regimes.csv, .md and .png go.", required=True)
flags.DEFINE_string("reference", "sfm_flow", "The method the model is compared with.")
flags.DEFINE_integer("num_bins", 3, "Quantile bins per property (3: terciles).", lower_bound=1)
common.define_data_flags(default_dataset=None)


def main(argv):
    del argv
    common.initialise()
    import data
    from data.gld_scenes import redraw
    from gld.analysis import regimes_run

    summary = regimes_run.write_regimes(
        FLAGS.workdir,
        FLAGS.output_dir,
        get_builder=lambda name: data.get_builder(name, FLAGS.data_dir),
        texture_reader=redraw.texture_reader,
        dataset=FLAGS.dataset,
        eval_dir=FLAGS.eval_dir,
        reference=FLAGS.reference,
        num_bins=FLAGS.num_bins,
    )
    print(summary)
    print(f"wrote {Path(FLAGS.output_dir)}/regimes.csv, regimes.md, regimes.png")


if __name__ == "__main__":
    common.run(main)
