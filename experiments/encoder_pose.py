r"""Trains the global encoder directly on the true relative pose: how fast can it learn it?

    python -m experiments.encoder_pose [--encoder_norm=instance] [--nouse_image_pair]
        [--encoder_coordinates]
        [--steps=600] [--flow_source=gt] [--out=runs/encoder_pose/<name>.json]

A capacity check of the global module, not a depth model (`gld.analysis.probes.
train_encoder_on_pose`): the encoder and a 256-256 MLP head regress [10 x the rotation
vector, the translation direction] of the training pairs (L1, Adam with warm-up and
cosine decay); the test pairs are scored in degrees next to their mean pose. Prints the
errors and writes them as JSON.
"""

from __future__ import annotations

import json
from pathlib import Path

from absl import app, flags

from experiments import common
from gld import files, options
from gld.analysis import encoder_pose
from gld.models.global_local import GlobalLocal
from gld.runs.config import TrainConfig

FLAGS = flags.FLAGS

# The encoder's options and the training options this check reads, each the model's or
# the trainer's option (its help and bounds), with this check's defaults.
ENCODER_OPTIONS = ("encoder_norm", "use_image_pair", "encoder_coordinates", "flow_scale")
TRAINING_OPTIONS = ("steps", "batch_size", "learning_rate", "warmup_steps", "seed", "flow_source")
common.define_option_flags(
    [field for field in options.option_fields(GlobalLocal) if field.name in ENCODER_OPTIONS]
)
common.define_option_flags(
    [field for field in options.option_fields(TrainConfig) if field.name in TRAINING_OPTIONS],
    {"steps": 600, "learning_rate": 1e-3, "warmup_steps": 50, "flow_source": "gt"},
)
flags.DEFINE_string("out", None, "JSON file for the errors (default: not written).")
common.define_data_flags()


def main(argv):
    del argv
    common.initialise()
    from gld.runs import optimizer

    try:
        optimizer.check_schedule("cosine", FLAGS.warmup_steps, FLAGS.steps)
    except ValueError as error:
        raise app.UsageError(str(error)) from None
    builder = common.prepare_dataset()
    errors = encoder_pose.train_encoder_on_pose(
        common.data_source(builder, "train"),
        common.data_source(builder, "test"),
        steps=FLAGS.steps,
        encoder_norm=FLAGS.encoder_norm,
        use_image_pair=FLAGS.use_image_pair,
        encoder_coordinates=FLAGS.encoder_coordinates,
        flow_source=FLAGS.flow_source,
        flow_scale=FLAGS.flow_scale,
        batch_size=FLAGS.batch_size,
        learning_rate=FLAGS.learning_rate,
        warmup_steps=FLAGS.warmup_steps,
        seed=FLAGS.seed,
    )
    for name, values in errors.items():
        print(
            f"{name}: rotation {values['rotation_deg']:.2f} deg, "
            f"translation direction {values['translation_deg']:.2f} deg"
        )
    if FLAGS.out:
        files.write_atomically(Path(FLAGS.out), json.dumps(errors, indent=2) + "\n")
        print(f"wrote {FLAGS.out}")


if __name__ == "__main__":
    common.run(main)
