r"""Where a self-supervised run's depth error comes from: scale, shape or pose.

    python -m experiments.diagnose_self_supervised \
        --workdirs=runs/paper_cpu_full/runs/struct2depth_low_lr[,...] [--split=test]

Prints, per workdir, on the split's pairs (`gld.analysis.self_supervised_diagnosis`): Abs-Inv and
S-RMSE as scored (units of the predicted translation) and with each pair's scale from the
truth, beside the per-pair oracle constant; the pose errors in degrees beside predicting no
rotation. Then, once for the dataset, the photometric loss at the true depth and pose and
at spoiled truths. Writes <workdir>/eval/self_supervised_diagnosis.json per workdir.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from absl import app, flags

from experiments import common

FLAGS = flags.FLAGS

flags.DEFINE_list("workdirs", [], "Self-supervised training workdirs to diagnose.")
flags.DEFINE_string("split", "test", "Split to diagnose on.")
flags.DEFINE_integer("max_examples", 0, "Use the first N pairs of the split (0 = all).")
flags.DEFINE_integer("batch_size", 16, "Batch size of the forward passes.")
common.define_data_flags(default_dataset=None)


def main(argv):
    del argv
    common.initialise()
    from gld.analysis import self_supervised_diagnosis as diagnosis
    from gld.evaluation import evaluate as evaluation
    from gld.models.baselines import classical
    from gld.runs import workdir as workdir_lib

    if not FLAGS.workdirs:
        raise app.UsageError("--workdirs names no workdir")
    missing = [w for w in FLAGS.workdirs if not Path(w).is_dir()]
    if missing:
        raise app.UsageError(f"--workdirs: no such directory: {', '.join(missing)}")
    trained = [workdir_lib.load_trained(w) for w in FLAGS.workdirs]
    datasets = {config.dataset for _, _, config in trained}
    if FLAGS.dataset is None and len(datasets) > 1:
        raise app.UsageError(f"the workdirs were trained on {sorted(datasets)}: give --dataset")
    source = common.data_source(
        common.prepare_dataset(FLAGS.dataset or datasets.pop()), FLAGS.split
    )

    def batches(flow_source="estimated"):
        return evaluation.split_batches(
            source,
            batch_size=FLAGS.batch_size,
            flow_source=flow_source,
            max_examples=FLAGS.max_examples,
            progress=False,
            all_processes=False,
        )

    oracle, _ = evaluation.evaluate_predictor(
        classical.OraclePairMedian().predict, source, max_examples=FLAGS.max_examples
    )
    oracle_abs_inv = float(np.mean(oracle["abs_inv"][oracle["example_mask"]]))
    at_truth = diagnosis.photometric_at_truth(batches())
    for workdir, (model, variables, config) in zip(FLAGS.workdirs, trained, strict=True):
        per_pair = diagnosis.diagnose_model(model, variables, batches(config.flow_source))
        summary = {name: float(np.mean(values)) for name, values in per_pair.items()}
        summary.update(
            {
                f"{name}_median": float(np.median(per_pair[name]))
                for name in ("rotation_deg", "translation_deg", "identity_rotation_deg")
            },
            oracle_abs_inv=oracle_abs_inv,
            pairs=len(per_pair["abs_inv"]),
        )
        print(
            f"{workdir}: Abs-Inv {summary['abs_inv']:.4f} as scored, "
            f"{summary['abs_inv_median_scaled']:.4f} at the truth's scale "
            f"(per-pair oracle constant {oracle_abs_inv:.4f}); S-RMSE {summary['s_rmse']:.3f}; "
            f"median pose error: rotation {summary['rotation_deg_median']:.2f} deg "
            f"(no rotation: {summary['identity_rotation_deg_median']:.2f}), "
            f"translation direction {summary['translation_deg_median']:.1f} deg"
        )
        out = Path(workdir) / "eval"
        out.mkdir(parents=True, exist_ok=True)
        report = {"split": FLAGS.split, "summary": summary, "photometric_at_truth": at_truth}
        (out / "self_supervised_diagnosis.json").write_text(json.dumps(report, indent=2) + "\n")
    for name, terms in at_truth.items():
        print(
            f"photometric loss, {name}: {terms['photometric']:.4f} "
            f"(auto-mask {terms['auto_mask_fraction']:.3f})"
        )


if __name__ == "__main__":
    common.run(main)
