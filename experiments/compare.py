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
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

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
common.define_data_flags()
common.define_flow_net_flags()


def _finished_step(workdir: Path) -> int | None:
    """The last checkpointed step of a run directory, or None."""
    from gld.runs import checkpoints as checkpoint_lib

    if not (workdir / "checkpoints").exists():
        return None
    manager = checkpoint_lib.checkpoint_manager(workdir)
    step = manager.latest_step()
    manager.close()
    return step


def run_comparison(
    *,
    workdir: str | Path,
    builder,
    models: Sequence[str],
    classical_methods: Sequence[str],
    train_config: dict[str, Any],
    split: str = "test",
    eval_batch_size: int = 16,
    max_examples: int = 0,
    model_configs: dict[str, dict[str, Any]] | None = None,
    print_fn: Callable[[str], None] = print,
) -> dict[str, Any]:
    """Trains (or reuses) each learned model, evaluates all methods, writes the table.

    Args:
      workdir: <workdir>/<model> holds each model's run, <workdir>/compare the results.
      builder: the dataset's TFDS builder (built).
      models: names in gld.models.registry.MODELS.
      classical_methods: names in gld.models.baselines.CLASSICAL; the references of every
        evaluation (`gld.evaluation.evaluate.REFERENCES`) are evaluated, first among them, whether
        listed or not: a table carries its references.
      train_config: gld.runs.config.TrainConfig fields shared by every model (budget, seed,
        loss weights, supervision, flow, ...); `model`, dataset and size are set here.
      split: the evaluation split.
      eval_batch_size, max_examples: evaluation batching; 0 examples = the whole split.
      model_configs: model name -> its constructor options (default: the model's
        defaults), e.g. the flow network's run of `global_local_flow_net`.
      print_fn: progress messages.

    Returns:
      The content of results.json.
    """
    from gld.evaluation import evaluate as evaluation
    from gld.evaluation import metrics, trained_run
    from gld.models import registry
    from gld.models.baselines import CLASSICAL
    from gld.models.baselines.classical import LABELS
    from gld.runs import config
    from gld.runs import workdir as workdir_lib
    from gld.training import trainer as train

    for name in models:
        if name not in registry.MODELS:
            raise ValueError(f"unknown model {name!r}; valid: {sorted(registry.MODELS)}")
    for name in classical_methods:
        if name not in CLASSICAL:
            raise ValueError(f"unknown classical method {name!r}; valid: {sorted(CLASSICAL)}")
    references = list(evaluation.REFERENCES)
    classical_methods = [*references, *(m for m in classical_methods if m not in references)]
    workdir = Path(workdir)
    height, width = common.dataset_resolution(builder)
    train_source = common.data_source(builder, "train")
    eval_source = common.data_source(builder, split)
    flow_source = train_config.get("flow_source", "estimated")

    results: dict[str, dict] = {}
    runs: dict[str, dict] = {}
    num_examples = 0
    for name in models:
        run_config = config.TrainConfig(
            **train_config,
            model=name,
            model_config=dict((model_configs or {}).get(name, {})),
            dataset=builder.info.full_name,
            height=height,
            width=width,
        )
        run_dir = workdir / name
        done = _finished_step(run_dir)
        started = time.perf_counter()
        if done is not None and done >= run_config.steps:
            print_fn(f"{name}: reusing the finished run in {run_dir} (step {done})")
            train_seconds = None
        else:
            print_fn(f"{name}: training {run_config.steps} steps in {run_dir}")
            train.train_and_evaluate(
                run_config, run_dir, train_source, eval_source, print_fn=print_fn
            )
            train_seconds = time.perf_counter() - started
        model, variables, saved = workdir_lib.load_trained(run_dir)
        per_example, _ = evaluation.evaluate_source(
            model,
            variables,
            eval_source,
            batch_size=eval_batch_size,
            flow_source=flow_source,
            max_examples=max_examples,
        )
        results[name], num_examples = evaluation.summarise_examples(per_example)
        runs[name] = {
            "workdir": str(run_dir),
            "parameters": registry.parameter_counts(variables["params"])["total"],
            "steps": int(_finished_step(run_dir)),
            "batch_size": saved.batch_size,
            "train_seconds": train_seconds,
        }

    for name in classical_methods:
        print_fn(f"{name}: evaluating")
        started = time.perf_counter()
        method = trained_run.fit_classical(name, train_source, flow_source)
        per_example, _ = evaluation.evaluate_predictor(
            method.predict,
            eval_source,
            batch_size=eval_batch_size,
            flow_source=flow_source,
            max_examples=max_examples,
        )
        results[name], num_examples = evaluation.summarise_examples(per_example)
        runs[name] = {"parameters": 0, "steps": 0, "eval_seconds": time.perf_counter() - started}
        if "failed" in results[name]:
            failed = results[name]["failed"]
            runs[name]["failed_pairs"] = round(failed["mean"] * failed["count"])

    budget = (
        f"learned models: {train_config.get('steps')} steps at batch "
        f"{train_config.get('batch_size')}, {train_config.get('gt_pixels')} supervised "
        f"pixel(s) per image, seed {train_config.get('seed')}; {flow_source} flow for every method"
    )
    stamp = metrics.protocol_stamp(height, width, num_examples, extra=budget)
    report = {
        "protocol": stamp,
        "dataset": builder.info.full_name,
        "split": split,
        "train_config": dict(train_config),
        "methods": results,
        "labels": {name: label for name, label in LABELS.items() if name in results},
        "abs_inv_vs_dataset_mean": metrics.ratios_to_reference(results.items()),
        "runs": runs,
    }
    out_dir = workdir / "compare"
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / "results.json").write_text(json.dumps(report, indent=2) + "\n")
    table = metrics.markdown_table(results.items(), stamp, labels=LABELS)
    table += (
        "\n| method | parameters | steps | train time | failed pairs |\n|---|---|---|---|---|\n"
    )
    for name, run in runs.items():
        if name in classical_methods:
            train_time = "none"
        elif run["train_seconds"] is None:
            train_time = "reused"
        else:
            train_time = f"{run['train_seconds']:.0f} s"
        failed_pairs = run.get("failed_pairs", "—")
        table += (
            f"| {metrics.table_name(name, LABELS)} | {run['parameters']:,} | {run['steps']} "
            f"| {train_time} | {failed_pairs} |\n"
        )
    (out_dir / "table.md").write_text(table)
    print_fn(table)
    return report


def main(argv):
    del argv
    common.initialise()
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
    train_config = common.training_options()
    run_comparison(
        workdir=FLAGS.workdir,
        builder=builder,
        models=FLAGS.models,
        classical_methods=FLAGS.classical,
        train_config=train_config,
        split=FLAGS.split,
        eval_batch_size=FLAGS.eval_batch_size,
        max_examples=FLAGS.max_examples,
        model_configs=model_configs,
    )
    # Next to the table it produced: the flags that made it (a valid --flagfile).
    files.write_atomically(Path(FLAGS.workdir) / "compare" / "flags.txt", common.flags_file_text())


if __name__ == "__main__":
    app.run(main)
