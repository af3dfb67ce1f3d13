r"""Probes what a trained global-local model has learned, on the test pairs.

    python -m experiments.probe --workdir=runs/demo [--step=N] [--max_examples=N]

Prints and writes <workdir>/eval/probe.json:
- depth statistics: how each pair's mean predicted inverse depth follows the truth
  across pairs (the depth scale) and how the map correlates with the truth within a
  pair (the structure); see `gld.analysis.probes.depth_statistics`;
- the pose probe (the paper's Sec. 4.4): an MLP trained on the frozen global
  parameters of the training pairs regresses the relative pose of the test pairs;
  errors in degrees beside predicting the training mean pose;
- for a run trained with the epipolar term, g read directly as the pose the term trains
  it to be (`gld.analysis.probes.global_params_pose_errors`; translation direction up to sign).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from absl import flags

from experiments import common

FLAGS = flags.FLAGS

flags.DEFINE_string("workdir", "runs/demo", "Training workdir to probe.")
flags.DEFINE_integer("step", None, "Checkpoint step (default: latest).")
flags.DEFINE_integer("max_examples", 0, "Probe the first N pairs of each split (0 = all).")
flags.DEFINE_integer("batch_size", 16, "Batch size of the forward passes.")
flags.DEFINE_bool("pose_probe", True, "Fit the pose probe on the training pairs.")
flags.DEFINE_integer("probe_steps", 2000, "Full-batch Adam steps of the pose probe.")
common.define_data_flags(default_dataset=None)
common.define_flow_source_flag()


def main(argv):
    del argv
    common.initialise()
    import jax

    from gld.analysis import probes
    from gld.runs import workdir as workdir_lib

    model, variables, config = workdir_lib.load_trained(FLAGS.workdir, step=FLAGS.step)
    builder = common.prepare_dataset(FLAGS.dataset or config.dataset)
    flow_source = FLAGS.flow_source or config.flow_source

    from gld.models import layers

    @jax.jit
    def forward(variables, batch):
        outputs = layers.apply_model(model, variables, batch, train=False)
        return {k: outputs[k] for k in ("inv_depth", "global_params") if k in outputs}

    def apply_fn(batch):
        keys = layers.input_keys(model)
        return forward(variables, {key: batch[key] for key in keys})

    def run(split):
        return probes.collect(
            apply_fn,
            common.data_source(builder, split),
            batch_size=FLAGS.batch_size,
            flow_source=flow_source,
            max_examples=FLAGS.max_examples,
        )

    test = run("test")
    report = {
        "workdir": FLAGS.workdir,
        "flow_source": flow_source,
        "num_test_pairs": len(test["pred_mean"]),
    }
    report["depth"] = probes.depth_statistics(test)
    for name, value in report["depth"].items():
        print(f"{name}: {value:.4f}")
    poses = {}
    if FLAGS.pose_probe and "global_params" in test:
        poses = probes.pose_probe(run("train"), test, steps=FLAGS.probe_steps)
    if config.epipolar_weight > 0 and np.shape(test.get("global_params"))[1:] == (6,):
        poses["global_params_read_as_pose"] = probes.global_params_pose_errors(test)
    if poses:
        report["pose_probe"] = poses
        for name, errors in poses.items():
            print(
                f"pose from global params, {name}: rotation {errors['rotation_deg']:.2f} deg, "
                f"translation direction {errors['translation_deg']:.2f} deg"
            )
    out = Path(FLAGS.workdir) / "eval"
    out.mkdir(parents=True, exist_ok=True)
    (out / "probe.json").write_text(json.dumps(report, indent=2) + "\n")
    print(f"wrote {out / 'probe.json'}")


if __name__ == "__main__":
    common.run(main)
