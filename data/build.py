r"""Builds a gld dataset without TensorFlow (`tfds build` imports TensorFlow at start-up).

    python -m data.build --dataset=gld_scenes/full --workers=8
    python -m data.build --dataset=demon/sun3d --manual_dir=~/demon --max_bad_fraction=0.01
    python -m data.build --dataset=demon/sun3d --manual_dir=~/demon \
        --depth_resampling=centred --data_dir=datasets_gld_convention
    python -m data.build --dataset=demon/sun3d --manual_dir=~/demon --image_decoder=opencv \
        --data_dir=datasets_opencv_webp   # OpenCV's WebP decoding, not DeMoN's (no `webp`)

Launchers build on first use too; this command exposes the builders' options. A
built dataset is reused only for the files and options it was built from: given
another --manual_dir content or other options, the command stops and names the
differences. Then build into another --data_dir, or replace the dataset:

    python -m data.build --dataset=demon/custom --manual_dir=~/robot2 --rebuild

(the old dataset stays in place until the new build has succeeded).
"""

from __future__ import annotations

from absl import flags

import data
from data import command_line
from data.demon import images, pairs

FLAGS = flags.FLAGS

flags.DEFINE_string("dataset", "gld_scenes/small", "Dataset with config, e.g. gld_scenes/full.")
flags.DEFINE_string("data_dir", None, "Where built datasets live (default: ./datasets).")
flags.DEFINE_string("manual_dir", None, "Manual-download dir (DeMoN .h5 files).")
flags.DEFINE_bool(
    "rebuild",
    False,
    "Build again even if built (e.g. from changed --manual_dir files or with other "
    "options); the built dataset is replaced once the new build has succeeded.",
)
flags.DEFINE_integer("workers", None, "gld_scenes: rendering processes.")
flags.DEFINE_bool("strict", None, "demon: fail at the first damaged pair.")
flags.DEFINE_float("max_bad_fraction", None, "demon: fail when more pairs than this are bad.")
flags.DEFINE_bool("verify_checksums", None, "demon: check known files' published MD5 sums.")
flags.DEFINE_string(
    "flow_estimator",
    None,
    "The stored flow's estimator: dis, dis_fast, farneback, or flow_net:<workdir> of a network "
    "trained by experiments.train_flow (default: the dataset's, dis).",
)
flags.DEFINE_float(
    "min_relative_baseline",
    None,
    "demon: skip pairs whose baseline is at most this x the median depth, in every split "
    "(default: 1e-4 for train, 0 for test, which keeps every pair DeMoN evaluates).",
)
flags.DEFINE_enum(
    "depth_resampling",
    None,
    sorted(pairs.DEPTH_RESAMPLING),
    "demon: depth resampling, 'demon' (the default: DeMoN's INTER_NEAREST) or 'centred' "
    "(centre-aligned, holes filled: keeps sparse range readings of recordings not at "
    "256x192).",
)
flags.DEFINE_enum(
    "image_decoder",
    None,
    list(images.IMAGE_DECODERS),
    "demon: WebP decoding, 'demon' (the default: libwebp as DeMoN's C++ reader; lossy "
    "images need the webp package, without which the build is refused) or 'opencv' "
    "(OpenCV's decoding, which approximates DeMoN's images).",
)


def main(argv):
    del argv
    names = ("workers", "strict", "max_bad_fraction", "verify_checksums", "flow_estimator")
    names += ("min_relative_baseline", "depth_resampling", "image_decoder")
    options = {name: FLAGS[name].value for name in names if FLAGS[name].value is not None}
    builder = data.prepare(
        FLAGS.dataset, FLAGS.data_dir, FLAGS.manual_dir, rebuild=FLAGS.rebuild, **options
    )
    for split, info in builder.info.splits.items():
        print(f"{FLAGS.dataset} {split}: {info.num_examples} pairs")
    print(f"built in {builder.data_dir}")


if __name__ == "__main__":
    command_line.run(main)
