"""Depth methods compared on one dataset: every learned model trained with the same
budget, seed, loss, optimiser and input pipeline, and every classical method fitted, all
scored on the same split with the same flow (`python -m experiments.compare`).

    run_comparison(workdir="runs/compare_small", dataset=..., train_source=...,
                   eval_source=..., height=96, width=128, models=["global_local"],
                   classical_methods=["sfm_flow"], train_config={"steps": 2500, ...})

Each learned model's run is <workdir>/<model>, trained once (`gld.training.scored_run`:
a finished run is reused, an unfinished one resumed). <workdir>/compare/ receives:
  table.md      rows = methods; Abs-Inv, Abs-Rel, S-RMSE as mean ± std over examples,
                Abs-Inv as a multiple of the dataset mean's, the protocol stamp, and each
                method's parameters, training and failures;
  results.json  the same numbers (every per-example metric's mean, std and count).

Every method is scored against the records' ground truth, or, with `truth` (a demon/*
dataset's DeMoN files, `gld.evaluation.evaluation_run.open_truth`), against the truth it
looks up by id at its files' resolution, as `python -m experiments.evaluate` scores it
(the oracle takes its constant from that truth); the stamp says which, and names the
records' protocol (`records_protocol`).
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

from gld import input_pipeline
from gld.evaluation import evaluate as evaluation
from gld.evaluation import metrics, stored_predictions, trained_run
from gld.models import registry
from gld.models.baselines.classical import CLASSICAL, LABELS
from gld.runs import checkpoints as checkpoint_lib
from gld.runs import config
from gld.training import scored_run


def run_comparison(
    *,
    workdir: str | Path,
    dataset: str,
    train_source,
    eval_source,
    height: int,
    width: int,
    models: Sequence[str],
    classical_methods: Sequence[str],
    train_config: dict[str, Any],
    split: str = "test",
    eval_batch_size: int = 16,
    max_examples: int = 0,
    model_configs: dict[str, dict[str, Any]] | None = None,
    truth: evaluation.Truth | None = None,
    records_protocol: Mapping[str, Any] | None = None,
    print_fn: Callable[[str], None] = print,
) -> dict[str, Any]:
    """Trains (or reuses) each learned model, evaluates all methods, writes the table.

    Args:
      workdir: <workdir>/<model> holds each model's run, <workdir>/compare the results.
      dataset: the dataset's TFDS full name.
      train_source, eval_source: its training split and the evaluation split, as
        random-access record sources; `height`, `width`: its resolution.
      models: names in gld.models.registry.MODELS.
      classical_methods: names in gld.models.baselines.CLASSICAL; the references of every
        evaluation (`gld.evaluation.evaluate.REFERENCES`) are evaluated, first among them, whether
        listed or not: a table carries its references.
      train_config: gld.runs.config.TrainConfig fields shared by every model (budget, seed,
        loss weights, supervision, flow, ...); `model`, dataset and size are set here.
      split: the evaluation split's name.
      eval_batch_size, max_examples: evaluation batching; 0 examples = the whole split.
      model_configs: model name -> its constructor options (default: the model's
        defaults), e.g. the flow network's run of `global_local_flow_net`.
      truth: the ground truth every method is scored against, looked up by example id
        (checked here, before anything is trained); None: the records'.
      records_protocol: the build options that make the records' protocol, named in the
        stamp and results.json (`gld.evaluation.evaluation_run.records_protocol`).
      print_fn: progress messages.

    Raises:
      ValueError: an unknown model or method; `truth` cannot serve an example (before
        anything is trained).

    Returns:
      The content of results.json.
    """
    for name in models:
        if name not in registry.MODELS:
            raise ValueError(f"unknown model {name!r}; valid: {sorted(registry.MODELS)}")
    for name in classical_methods:
        if name not in CLASSICAL:
            raise ValueError(f"unknown classical method {name!r}; valid: {sorted(CLASSICAL)}")
    references = list(evaluation.REFERENCES)
    classical_methods = [*references, *(m for m in classical_methods if m not in references)]
    workdir = Path(workdir)
    flow_source = train_config.get("flow_source", "estimated")
    file_resolutions = None
    if truth is not None:
        truth.check(
            stored_predictions.record_ids_and_baselines(
                input_pipeline.first_records(eval_source, max_examples)
            )
        )
        file_resolutions = metrics.resolution_counts(truth.shapes().values())

    results: dict[str, dict] = {}
    runs: dict[str, dict] = {}
    num_examples = 0
    for name in models:
        run_config = config.TrainConfig(
            **train_config,
            model=name,
            model_config=dict((model_configs or {}).get(name, {})),
            dataset=dataset,
            height=height,
            width=width,
        )
        run_dir = workdir / name
        train_seconds = scored_run.train_unless_finished(
            name, run_config, run_dir, train_source, eval_source, print_fn=print_fn
        )
        scored = scored_run.score(
            run_dir,
            eval_source,
            batch_size=eval_batch_size,
            flow_source=flow_source,
            max_examples=max_examples,
            truth=truth,
        )
        results[name], num_examples = evaluation.summarise_examples(scored.per_example)
        runs[name] = {
            "workdir": str(run_dir),
            "parameters": scored.parameters,
            "steps": checkpoint_lib.last_checkpointed_step(run_dir),
            "batch_size": scored.config.batch_size,
            "train_seconds": train_seconds,
        }

    for name in classical_methods:
        print_fn(f"{name}: evaluating")
        started = time.perf_counter()
        method = trained_run.fit_classical(name, train_source, flow_source)
        predict = method.predict
        if truth is not None and name == evaluation.ORACLE:
            predict = trained_run.on_truth(predict, truth)
        per_example, _ = evaluation.evaluate_predictor(
            predict,
            eval_source,
            batch_size=eval_batch_size,
            flow_source=flow_source,
            max_examples=max_examples,
            truth=truth,
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
    stamp = metrics.protocol_stamp(
        height,
        width,
        num_examples,
        extra=budget,
        truth_resolution="record" if truth is None else "file",
        file_resolutions=file_resolutions,
        records_protocol=records_protocol,
    )
    report = {
        "protocol": stamp,
        "dataset": dataset,
        "split": split,
        "truth_resolution": "record" if truth is None else "file",
        **({} if truth is None else {"truth_resolutions": file_resolutions, **truth.summary()}),
        **({"records_protocol": dict(records_protocol)} if records_protocol else {}),
        "train_config": dict(train_config),
        "methods": results,
        "labels": {name: label for name, label in LABELS.items() if name in results},
        "abs_inv_vs_dataset_mean": metrics.ratios_to_reference(results.items()),
        "runs": runs,
    }
    out_dir = workdir / "compare"
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / "results.json").write_text(json.dumps(report, indent=2) + "\n")
    table = _table(results, runs, stamp, classical_methods)
    (out_dir / "table.md").write_text(table)
    print_fn(table)
    return report


def _table(
    results: dict[str, dict],
    runs: dict[str, dict],
    stamp: str,
    classical_methods: Sequence[str],
) -> str:
    """table.md: the metrics table, then each method's parameters, steps, training time
    and failed pairs."""
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
    return table
