r"""Evaluates a trained workdir or a classical baseline on a whole split.

    python -m experiments.evaluate --workdir=runs/demo
    python -m experiments.evaluate --model=triangulation_gt_pose --dataset=gld_scenes/small \
        --workdir=runs/triangulation [--flow=gt]

Writes <workdir>/eval/: metrics.json, table.md (mean ± std per metric, protocol stamp),
per_example_<method>.csv and figures/ (image 1, ground truth, prediction, error, the
supervised pixel circled; one colour scale for all).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from absl import app, flags

from experiments import common

FLAGS = flags.FLAGS

flags.DEFINE_string("workdir", "runs/demo", "Run directory; results go to <workdir>/eval.")
flags.DEFINE_string(
    "model", None, "A classical baseline (no training) instead of the workdir's model."
)
flags.DEFINE_string("split", "test", "Split to evaluate.")
flags.DEFINE_integer("batch_size", 16, "Evaluation batch size (last batch padded).")
flags.DEFINE_integer("num_figures", 8, "Example figures to draw.")
flags.DEFINE_integer("max_examples", 0, "Evaluate the first N examples only (0 = all).")
flags.DEFINE_bool("dataset_mean", True, "Also evaluate the dataset-mean baseline.")
flags.DEFINE_integer("step", None, "Checkpoint step to evaluate (default: latest).")
common.define_data_flags(default_dataset=None)
common.define_distributed_flags()


def _training_examples(builder, flow: str):
    from gld import input_pipeline

    return input_pipeline.eval_batches(
        builder.as_data_source("train"), batch_size=16, flow_source=flow
    )


def fit_classical(name: str, builder, flow: str):
    """A classical baseline, fitted on the training split when it needs to be."""
    from gld.baselines import classical

    if name not in classical.CLASSICAL:
        raise ValueError(f"unknown classical method {name!r}; valid: {sorted(classical.CLASSICAL)}")
    method = classical.CLASSICAL[name]()
    if method.needs_training_data:
        method.fit(
            {key: batch[key][batch["example_mask"]] for key in ("depth", "depth_valid")}
            for batch in _training_examples(builder, flow)
        )
    return method


def _figure_examples(source, count: int, gt_pixels: int, seed: int, flow: str, split: str):
    from gld import input_pipeline

    examples = []
    for index in range(min(count, len(source))):
        example = input_pipeline.prepare_example(
            source[index],
            epoch=0,
            seed=seed,
            gt_pixels=gt_pixels,
            where=f"{split}[{index}]",
            flow_source=flow,
            augment=False,
            fixed_sparse_pixels=True,
        )
        examples.append(example)
    return examples


def evaluate_workdir(
    workdir: str,
    builder,
    *,
    split: str = "test",
    num_figures: int = 8,
    with_dataset_mean: bool = True,
    batch_size: int = 16,
    max_examples: int = 0,
    step: int | None = None,
    classical_method: str | None = None,
    flow: str | None = None,
) -> dict:
    """Evaluates a workdir's model (or a classical method) and writes <workdir>/eval."""
    import jax

    from gld import evaluation, train

    height, width = common.dataset_resolution(builder)
    source = builder.as_data_source(split)
    results, info = {}, {"dataset": builder.info.full_name, "split": split}
    if classical_method:
        flow = flow or "estimated"
        method = fit_classical(classical_method, builder, flow)
        results[classical_method] = evaluation.evaluate_predictor(
            method.predict,
            source,
            batch_size=batch_size,
            flow=flow,
            max_examples=max_examples,
            progress=True,
        )
        predict_depth = lambda batch: method.predict(batch)["depth"]  # noqa: E731
        gt_pixels, seed = 1, 0
    else:
        model, variables, config = train.load_trained(workdir, step=step)
        flow = flow or config.flow
        results[config.model] = train.evaluate_source(
            model,
            variables,
            source,
            batch_size=batch_size,
            flow=flow,
            max_examples=max_examples,
            progress=True,
        )
        apply = jax.jit(lambda v, b: model.apply(v, b["image1"], b["image2"], b["flow"]))
        predict_depth = lambda batch: apply(variables, batch)["depth"]  # noqa: E731
        gt_pixels, seed = config.gt_pixels, config.seed
        info.update(
            model=config.model,
            gt_pixels=config.gt_pixels,
            flow=flow,
            step=int(train.checkpoint_manager(workdir).latest_step() if step is None else step),
        )
    if with_dataset_mean and jax.process_index() == 0:
        mean = fit_classical("dataset_mean", builder, flow)
        results["dataset_mean"] = evaluation.evaluate_predictor(
            mean.predict, source, batch_size=batch_size, flow=flow, max_examples=max_examples
        )
        info["dataset_mean_inv_depth"] = mean.inv_depth
    if jax.process_index() != 0:
        return {}
    out_dir = Path(workdir) / "eval"
    report = evaluation.write_report(out_dir, results, height=height, width=width, info=info)
    if num_figures:
        examples = _figure_examples(source, num_figures, gt_pixels, seed, flow, split)
        batch = {k: np.stack([e[k] for e in examples]) for k in ("image1", "image2", "flow")}
        predictions = np.asarray(predict_depth(batch))
        evaluation.render_examples(out_dir / "figures", examples, list(predictions))
    print((out_dir / "table.md").read_text())
    return report


def main(argv):
    del argv
    common.initialise_distributed()
    from gld import train

    if FLAGS.model:
        if not FLAGS.dataset:
            raise app.UsageError("--dataset is needed with --model")
        dataset = FLAGS.dataset
    else:
        config = train.load_run_config(FLAGS.workdir)
        dataset = FLAGS.dataset or config.dataset
    builder = common.prepare_dataset(dataset)
    evaluate_workdir(
        FLAGS.workdir,
        builder,
        split=FLAGS.split,
        num_figures=FLAGS.num_figures,
        with_dataset_mean=FLAGS.dataset_mean and FLAGS.model != "dataset_mean",
        batch_size=FLAGS.batch_size,
        max_examples=FLAGS.max_examples,
        step=FLAGS.step,
        classical_method=FLAGS.model,
        flow=FLAGS.flow if FLAGS["flow"].present or FLAGS.model else None,
    )


if __name__ == "__main__":
    app.run(main)
