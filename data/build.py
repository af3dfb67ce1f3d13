r"""Builds a gld dataset (TensorFlow-free; `tfds build`'s command line needs TensorFlow).

    python -m data.build --dataset=gld_scenes/full --workers=8
    python -m data.build --dataset=demon/sun3d --manual_dir=~/demon --max_bad_fraction=0.01

Launchers build on first use too; this command exposes the builders' options.
"""

from __future__ import annotations

from absl import app, flags

import data

FLAGS = flags.FLAGS

flags.DEFINE_string("dataset", "gld_scenes/small", "Dataset with config, e.g. gld_scenes/full.")
flags.DEFINE_string("data_dir", None, "Where built datasets live (default: ./datasets).")
flags.DEFINE_string("manual_dir", None, "Manual-download dir (DeMoN .h5 files).")
flags.DEFINE_integer("workers", None, "gld_scenes: rendering processes.")
flags.DEFINE_bool("strict", None, "demon: fail at the first damaged pair.")
flags.DEFINE_float("max_bad_fraction", None, "demon: fail when more pairs than this are bad.")
flags.DEFINE_bool("verify_checksums", None, "demon: check known files' published MD5 sums.")
flags.DEFINE_string("flow_estimator", None, "demon: flow estimator stored with the records.")


def main(argv):
    del argv
    options = {
        name: FLAGS[name].value
        for name in ("workers", "strict", "max_bad_fraction", "verify_checksums")
        if FLAGS[name].value is not None
    }
    if FLAGS.flow_estimator:
        options["flow_estimator"] = FLAGS.flow_estimator
    builder = data.prepare(FLAGS.dataset, FLAGS.data_dir, FLAGS.manual_dir, **options)
    for split, info in builder.info.splits.items():
        print(f"{FLAGS.dataset} {split}: {info.num_examples} pairs")
    print(f"built in {builder.data_dir}")


if __name__ == "__main__":
    app.run(main)
