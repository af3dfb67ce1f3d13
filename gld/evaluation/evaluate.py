"""Evaluation: one loop over a split for learned models and host-side methods alike.

`evaluate_source` runs a learned model (jit, sharded over a mesh, exact means over
padded batches); `evaluate_predictor` runs any host-side `predict(batch) -> {"depth",
...}` (the classical baselines and references). Both go through `evaluate_batches`, the
one loop, and score with `score_batch`, the one rule for which rows count. Training's
periodic evaluation, `experiments.evaluate`, `experiments.compare` and
`experiments.inspect_filters` read splits through `split_batches`. `evaluate_workdir`
evaluates a trained workdir (or a classical method, or depth maps another system stored,
`gld.evaluation.stored_predictions`) with its `REFERENCES` on the same examples and the same flow:
the dataset mean, the per-pair oracle constant and the classical pipeline (essential
matrix from the flow + triangulation) (`gld.evaluation.reports` writes it).

The ground truth is the records' (`score_batch`) unless a `Truth` is given: then each
example is scored against the truth it looks up by id, at that truth's resolution, the
prediction resized to it by centre-aligned nearest neighbour (`score_against_truth`;
DeMoN's evaluation at its files' resolution, `data.demon.file_truth`).
"""

from __future__ import annotations

import collections
import functools
import json
from collections.abc import Callable, Iterable, Iterator, Sequence
from pathlib import Path
from typing import Any, Protocol

import flax.linen as nn
import jax
import numpy as np
from jax.sharding import Mesh

from gld import input_pipeline, sharding
from gld.evaluation import metrics, reports, stored_predictions
from gld.models import layers
from gld.models.baselines import classical
from gld.runs import workdir as workdir_lib

# The per-pair oracle constant reported next to every method (`classical.OraclePairMedian`).
ORACLE = "oracle_pair_median"
# The classical pipeline on the same flow, reported next to every method: pose from the
# essential matrix of the flow, then triangulation; no training (`classical.SfMFlow`).
SFM = "sfm_flow"
# Every evaluation's references, in the order of its rows (after the evaluated method).
REFERENCES = ("dataset_mean", ORACLE, SFM)
# The table's name for depth maps another system stored.
STORED = "stored_predictions"

# Keys of an evaluation batch that go to the devices (the rest, like "id", stay on the host).
EVAL_KEYS = ("image1", "image2", "flow", "depth", "depth_valid", "example_mask")


class Truth(Protocol):
    """Ground truth at another resolution than the records', looked up by example id
    (`data.demon.file_truth.FileTruth` reads DeMoN's files)."""

    def check(self, examples: Iterable[tuple[str, float]]) -> None:
        """Finds the truth of every (id, ||t|| of its record) to be scored and remembers
        ||t||; raises naming every example it cannot serve, before anything is scored."""

    def shapes(self) -> dict[str, tuple[int, int]]:
        """id -> (height, width) of its truth, for every checked example."""

    def maps(self, ids: Sequence[str]) -> list[tuple[np.ndarray, np.ndarray]]:
        """(depth [h, w] float32 scaled so that ||t|| = 1, 0 where invalid; valid [h, w]
        bool) of each id, as `input_pipeline.prepare_example` makes a record's."""

    def summary(self) -> dict[str, Any]:
        """Fields metrics.json records about where the truth came from."""


def score_batch(depth: jax.Array, batch: dict) -> dict[str, jax.Array]:
    """Per-example metrics of predicted depth [B, H, W] against the batch's truth, with
    "example_mask": the rows that count (not padding, at least one valid ground-truth
    pixel), the same for every method whatever its predictions."""
    per_example = metrics.depth_metrics(depth, batch["depth"], batch["depth_valid"])
    return _with_example_mask(per_example, batch["example_mask"])


def _with_example_mask(per_example: dict, example_mask) -> dict:
    """Adds "example_mask": real rows with at least one valid ground-truth pixel."""
    truth_pixels = per_example["num_pixels"] + per_example["excluded_pixels"]
    per_example["example_mask"] = example_mask & (truth_pixels > 0)
    return per_example


# One compilation per truth resolution.
_depth_metrics = jax.jit(metrics.depth_metrics)


def score_against_truth(
    depth: Sequence[np.ndarray], ids: Sequence[str], example_mask: np.ndarray, truth: Truth
) -> dict[str, np.ndarray]:
    """Per-example metrics of predictions against `truth`'s maps, with "example_mask"
    by `score_batch`'s rule.

    Each prediction is resized to its truth's resolution by `metrics.resize_nearest`
    (the pixel under each truth pixel's centre, DeMoN's rule), then scored over the
    truth's pixels. Padded rows (mask False) are not looked up.

    Args:
      depth: B predicted depth maps [h, w] (a [B, h, w] array, or maps of any sizes).
      ids: [B] example ids.
      example_mask: [B] bool, the real rows.
      truth: where each id's ground truth comes from.
    """
    example_mask = np.asarray(example_mask, bool)
    if not len(depth) == len(ids) == len(example_mask):
        raise ValueError(f"{len(depth)} predictions for {len(ids)} ids")
    real = [str(i) for i, is_real in zip(ids, example_mask, strict=True) if is_real]
    truth_maps = iter(truth.maps(real))
    # A padded row is scored against one invalid pixel: no error, no pixel counted.
    no_truth = (np.zeros((1, 1), np.float32), np.zeros((1, 1), bool))
    rows = []
    for prediction, is_real in zip(depth, example_mask, strict=True):
        truth_depth, valid = next(truth_maps) if is_real else no_truth
        prediction = metrics.resize_nearest(np.asarray(prediction, np.float32), *valid.shape)
        rows.append(_depth_metrics(prediction[None], truth_depth[None], valid[None]))
    per_example = {
        name: np.concatenate([np.asarray(row[name]) for row in rows]) for name in rows[0]
    }
    return _with_example_mask(per_example, example_mask)


def make_eval_step(*, model: nn.Module) -> Callable[[dict, dict], dict]:
    """Builds the pure `eval_step(variables, batch) -> per-example metrics` ([B] each)."""

    def eval_step(variables: dict, batch: dict) -> dict:
        outputs = layers.apply_model(model, variables, batch, train=False)
        return score_batch(outputs["depth"], batch)

    return eval_step


def make_predict_step(*, model: nn.Module) -> Callable[[dict, dict], dict]:
    """Builds the pure `predict_step(variables, batch) -> {"depth", "example_mask"}`, for
    scoring on the host against a `Truth`."""

    def predict_step(variables: dict, batch: dict) -> dict:
        outputs = layers.apply_model(model, variables, batch, train=False)
        return {"depth": outputs["depth"], "example_mask": batch["example_mask"]}

    return predict_step


def jit_eval_step(eval_step: Callable, mesh: Mesh) -> Callable:
    """`eval_step` compiled with replicated variables and a sharded batch."""
    jitted = jax.jit(
        eval_step,
        in_shardings=(sharding.replicated(mesh), sharding.batch_sharded(mesh)),
        out_shardings=sharding.batch_sharded(mesh),
    )
    return sharding.under_mesh(jitted, mesh)


def split_batches(
    source,
    *,
    batch_size: int,
    flow_source: str = "estimated",
    max_examples: int = 0,
    keys: Sequence[str] | None = None,
    progress: bool = False,
    all_processes: bool = True,
) -> Iterator[dict[str, np.ndarray]]:
    """Unaugmented, padded batches of a split (or of its first `max_examples` records):
    this process's share when `all_processes`, else every batch (a host-side method on
    one process), with only `keys` and "id" when given (`input_pipeline.eval_batches`).
    Process 0 shows a progress bar when asked."""
    if max_examples:
        source = input_pipeline.first_records(source, max_examples)
    process_index, process_count = (
        (jax.process_index(), jax.process_count()) if all_processes else (0, 1)
    )
    batches = input_pipeline.eval_batches(
        source,
        batch_size=batch_size,
        flow_source=flow_source,
        keys=keys,
        process_index=process_index,
        process_count=process_count,
    )
    if progress and jax.process_index() == 0:
        from tqdm import tqdm

        total = input_pipeline.num_eval_batches(len(source), batch_size, process_count)
        batches = tqdm(batches, total=total, desc="evaluate", unit="batch", leave=False)
    return batches


def evaluate_batches(
    batches,
    score: Callable[[dict[str, np.ndarray], list[str]], dict[str, Any]],
    *,
    all_processes: bool = True,
) -> tuple[dict[str, np.ndarray], list[str]]:
    """The evaluation loop: `score(batch, ids)` ([B]-shaped values incl. "example_mask")
    over all batches, concatenated, with the examples' ids. When `all_processes`, `ids`
    are every process's rows (gathered once per batch), as `score` then returns them."""
    collected: dict[str, list] = {}
    all_ids: list[str] = []
    for batch in batches:
        ids = sharding.gather_strings(batch["id"]) if all_processes else list(map(str, batch["id"]))
        for name, values in score(batch, ids).items():
            collected.setdefault(name, []).append(np.asarray(values))
        all_ids.extend(ids)
    return {name: np.concatenate(values) for name, values in collected.items()}, all_ids


def evaluate_source(
    model: nn.Module,
    variables: dict,
    source,
    *,
    batch_size: int,
    flow_source: str = "estimated",
    mesh: Mesh | None = None,
    max_examples: int = 0,
    eval_step: Callable | None = None,
    progress: bool = False,
    truth: Truth | None = None,
) -> tuple[dict[str, np.ndarray], list[str]]:
    """Per-example metrics of a learned model over a whole split (or its first
    `max_examples`), on all devices of all processes.

    With `truth` (checked), the devices predict and every process scores the global
    batch on the host (`score_against_truth`); no `eval_step` may then be given.

    Returns:
      (name -> [N] values incl. "example_mask", ids [N]); padded rows have mask False.
    """
    if truth is not None and eval_step is not None:
        raise ValueError("give eval_step or truth, not both (truth is scored on the host)")
    mesh = mesh or sharding.make_mesh()
    batch_size = sharding.evaluation_batch_size(batch_size, mesh)
    local_batch = sharding.per_process_batch_size(batch_size, mesh)
    variables = jax.device_put(variables, sharding.replicated(mesh))
    keys = layers.with_input_keys(model, EVAL_KEYS)
    if truth is None:
        eval_step = eval_step or jit_eval_step(make_eval_step(model=model), mesh)

        def score(batch, ids):
            device_batch = sharding.to_global_batch(batch, mesh, keys)
            return sharding.gather(eval_step(variables, device_batch))

    else:
        predict_step = jit_eval_step(make_predict_step(model=model), mesh)

        def score(batch, ids):
            device_batch = sharding.to_global_batch(batch, mesh, keys)
            outputs = sharding.gather(predict_step(variables, device_batch))
            return score_against_truth(outputs["depth"], ids, outputs["example_mask"], truth)

    batches = split_batches(
        source,
        batch_size=local_batch,
        flow_source=flow_source,
        max_examples=max_examples,
        keys=keys,
        progress=progress,
    )
    return evaluate_batches(batches, score)


def evaluate_predictor(
    predict: Callable[[dict[str, np.ndarray]], dict[str, Any]],
    source,
    *,
    batch_size: int = 16,
    flow_source: str = "estimated",
    max_examples: int = 0,
    progress: bool = False,
    truth: Truth | None = None,
) -> tuple[dict[str, np.ndarray], list[str]]:
    """Per-example metrics of a host-side predictor over a split (single process).

    `predict` gets an example-contract batch (numpy) and returns at least "depth"
    [B, H, W] (with `truth`, which is checked: B maps of any sizes, see
    `score_against_truth`); any other [B]-shaped outputs (e.g. "failed") are kept per
    example.
    """
    jit_score = jax.jit(score_batch)

    def score(batch, ids):
        outputs = predict(batch)
        if truth is None:
            record_truth = {k: batch[k] for k in ("depth", "depth_valid", "example_mask")}
            per_example = jit_score(outputs["depth"], record_truth)
        else:
            per_example = score_against_truth(outputs["depth"], ids, batch["example_mask"], truth)
        per_example = {key: np.asarray(value) for key, value in per_example.items()}
        for key, value in outputs.items():
            if key == "depth" or key in per_example:
                continue
            value = np.asarray(value)
            if value.shape == (len(batch["id"]),):
                per_example[key] = value.astype(np.float64)
        return per_example

    batches = split_batches(
        source,
        batch_size=batch_size,
        flow_source=flow_source,
        max_examples=max_examples,
        progress=progress,
        all_processes=False,
    )
    return evaluate_batches(batches, score, all_processes=False)


def summarise_examples(per_example: dict[str, np.ndarray]) -> tuple[dict[str, dict], int]:
    """(`metrics.summarise` of the real examples, their number) of an evaluation's
    per-example values (with "example_mask")."""
    per_example = dict(per_example)
    mask = np.asarray(per_example.pop("example_mask"), bool)
    return metrics.summarise(per_example, mask), int(mask.sum())


def fit_classical(name: str, train_source, flow_source: str = "estimated"):
    """A classical baseline by name, fitted on the training split when it needs to be.

    Raises:
      ValueError: an unknown name, or a method that needs the training split without one.
    """

    if name not in classical.CLASSICAL:
        raise ValueError(f"unknown classical method {name!r}; valid: {sorted(classical.CLASSICAL)}")
    method = classical.CLASSICAL[name]()
    if method.needs_training_data:
        if train_source is None:
            raise ValueError(f"{name} is fitted on the training split, and none was given")
        # Only the truth is read: the other fields are neither flipped nor batched.
        fit_keys = ("depth", "depth_valid")
        batches = split_batches(
            train_source,
            batch_size=16,
            flow_source=flow_source,
            keys=fit_keys,
            all_processes=False,
        )
        method.fit(
            {key: batch[key][batch["example_mask"]] for key in fit_keys} for batch in batches
        )
    return method


def _fit_reference(name: str, train_source, flow_source: str, fitted: dict[str, Any]):
    """A reference (or the evaluated classical method), fitted once: the classical
    pipeline's fallback for failed pairs is the dataset mean's value when that is fitted
    already (`SfMFlow.fit` computes the same mean), and the fixed
    `layers.INITIAL_INV_DEPTH` when there is no training split."""

    if name == SFM and "dataset_mean" in fitted:
        return classical.SfMFlow(fallback_inv_depth=fitted["dataset_mean"].inv_depth)
    if name == SFM and train_source is None:
        return classical.SfMFlow(fallback_inv_depth=layers.INITIAL_INV_DEPTH)
    return fit_classical(name, train_source, flow_source)


def on_truth(predict: Callable[[dict], dict], truth: Truth) -> Callable[[dict], dict]:
    """A predictor that reads the batch's ground truth (the per-pair oracle), given each
    example's `truth` instead: its [h, w] maps at the truth's resolution."""

    def predict_on_truth(batch: dict) -> dict[str, list[np.ndarray]]:
        maps = truth.maps([str(example_id) for example_id in batch["id"]])
        return {
            "depth": [
                np.asarray(predict({"depth": depth[None], "depth_valid": valid[None]})["depth"])[0]
                for depth, valid in maps
            ]
        }

    return predict_on_truth


def _figure_examples(source, count: int, gt_pixels: int, seed: int, flow_source: str, split: str):
    return [
        input_pipeline.prepare_example(
            source[index],
            epoch=0,
            seed=seed,
            gt_pixels=gt_pixels,
            flow_source=flow_source,
            augment=False,
            fixed_sparse_pixels=True,
            # Every field, the derived pose from the flow too (a model may read it).
            keys=[key for key in input_pipeline.CONTRACT_KEYS if key != "id"],
            where=f"{split}[{index}]",
        )
        for index in range(min(count, len(source)))
    ]


# What makes two evaluations the same one: a folder holds one of them, whatever step.
EVALUATION_IDENTITY = ("dataset", "split", "model", "flow_source", "truth_resolution", "examples")


def evaluation_dir(
    workdir: str | Path,
    *,
    split: str = "test",
    max_examples: int = 0,
    step: int | None = None,
    flow_source: str | None = None,
    truth_resolution: str = "record",
    dataset: str | None = None,
) -> Path:
    """Where an evaluation is written: <workdir>/eval for the workdir's own evaluation
    (latest checkpoint, whole test split, its own flow and dataset, the records' truth),
    else <workdir>/eval_<what differs>, e.g. eval_train_first2, eval_step500_flow-gt,
    so that an evaluation never replaces a different one."""
    parts = []
    if dataset:
        parts.append("-".join(dataset.split("/")[:2]))
    if split != "test":
        parts.append(split)
    if max_examples:
        parts.append(f"first{max_examples}")
    if step is not None:
        parts.append(f"step{step}")
    if flow_source:
        parts.append(f"flow-{flow_source}")
    if truth_resolution != "record":
        parts.append(f"truth-{truth_resolution}")
    return Path(workdir) / "_".join(["eval", *parts])


def _same_dataset(evaluated: str, trained: str) -> bool:
    """Whether 'name/config[/version]' names the dataset a run was trained on."""
    return not evaluated or not trained or evaluated.split("/")[:2] == trained.split("/")[:2]


def _check_identity(out_dir: Path, info: dict[str, Any]) -> None:
    """Refuses to write over an evaluation of something else (another dataset, say)."""
    path = out_dir / "metrics.json"
    if not path.exists():
        return
    stored = json.loads(path.read_text())
    differing = {
        key: (stored.get(key), info.get(key))
        for key in EVALUATION_IDENTITY
        if key in stored and stored.get(key) != info.get(key)
    }
    if differing:
        details = ", ".join(
            f"{k}: {old!r} there vs {new!r} now" for k, (old, new) in differing.items()
        )
        raise ValueError(
            f"{out_dir} holds a different evaluation ({details}); it is kept: evaluate into "
            "another --workdir"
        )


def evaluate_workdir(
    workdir: str | Path,
    source,
    *,
    train_source=None,
    dataset: str = "",
    height: int,
    width: int,
    split: str = "test",
    num_figures: int = 8,
    with_dataset_mean: bool = True,
    with_oracle: bool = True,
    with_sfm_flow: bool = True,
    batch_size: int = 16,
    max_examples: int = 0,
    step: int | None = None,
    classical_method: str | None = None,
    predictions: stored_predictions.StoredPredictions | None = None,
    flow_source: str | None = None,
    truth: Truth | None = None,
    print_fn: Callable[[str], None] = print,
) -> dict[str, Any]:
    """Evaluates a workdir's trained model (or a classical method, or stored predictions)
    on `source`.

    Writes <workdir>/eval (`gld.evaluation.reports`). The `REFERENCES` are evaluated alongside on
    the same examples with the same flow (the workdir's unless `flow_source` is given),
    each when asked and unless it is the evaluated method itself: the dataset mean
    (fitted on `train_source`, so only when it is given), the per-pair oracle constant
    and the classical pipeline `sfm_flow` (pose and depth from the flow alone; its
    failed pairs fall back to the dataset mean, or to `layers.INITIAL_INV_DEPTH` without
    `train_source`, which metrics.json records). Rows: the method (`STORED` for
    `predictions`), then dataset_mean, oracle_pair_median, sfm_flow. The references are
    host-side methods: process 0 evaluates them, on every example.

    A folder already holding this evaluation (same `EVALUATION_IDENTITY`, whatever its
    references) is rewritten with this run's rows only (`reports.write_report`).

    Every method is scored against the records' ground truth at (height, width), or,
    with `truth`, against the truth it looks up by id (`score_against_truth`; stored
    predictions are then resized straight to each truth's resolution, and the oracle
    takes its constant from that truth); the stamp says which.

    Raises:
      FileNotFoundError, ValueError: `truth` cannot serve an example, or `predictions`
        lack a file or hold a bad one (`StoredPredictions.check`), before anything is
        evaluated or written.
    """
    results = {}
    fitted: dict[str, Any] = {}
    examples_count = min(max_examples, len(source)) if max_examples else len(source)
    info = {"dataset": dataset, "split": split, "examples": examples_count}
    protocol_note = ""
    if truth is not None or predictions is not None:
        examples = stored_predictions.record_ids_and_baselines(
            input_pipeline.first_records(source, max_examples)
        )
    file_resolutions = None
    if truth is not None:
        truth.check(examples)
        file_resolutions = dict(
            collections.Counter(f"{w}x{h}" for h, w in truth.shapes().values()).most_common()
        )
        info.update(truth_resolution="file", truth_resolutions=file_resolutions)
        info.update(truth.summary())
    else:
        info["truth_resolution"] = "record"

    def host_predictor(method_name: str, predict: Callable) -> Callable:
        return on_truth(predict, truth) if truth is not None and method_name == ORACLE else predict

    if classical_method or predictions is not None:
        flow_source = flow_source or "estimated"
        if predictions is not None:
            method, name = predictions, STORED
            predictions.check(
                examples,
                height=height,
                width=width,
                shapes=truth.shapes() if truth is not None else None,
            )
            protocol_note = predictions.protocol_note()
            info.update(predictions.summary())
        else:
            method = _fit_reference(classical_method, train_source, flow_source, fitted)
            fitted[classical_method] = method
            name = classical_method
        out_dir = evaluation_dir(
            workdir,
            split=split,
            max_examples=max_examples,
            step=step,
            flow_source=None if flow_source == "estimated" else flow_source,
            truth_resolution=info["truth_resolution"],
        )
        _check_identity(out_dir, {**info, "model": name, "flow_source": flow_source})
        predict = host_predictor(name, method.predict)
        results[name] = evaluate_predictor(
            predict,
            source,
            batch_size=batch_size,
            flow_source=flow_source,
            max_examples=max_examples,
            progress=True,
            truth=truth,
        )
        predict_depth = lambda batch: predict(batch)["depth"]  # noqa: E731
        gt_pixels, seed = 1, 0
        info.update(model=name, flow_source=flow_source)
    else:
        model, variables, config, restored_step = workdir_lib.restore_trained(workdir, step=step)
        own_flow, flow_source = (
            flow_source in (None, config.flow_source),
            flow_source or config.flow_source,
        )
        out_dir = evaluation_dir(
            workdir,
            split=split,
            max_examples=max_examples,
            step=step,
            flow_source=None if own_flow else flow_source,
            truth_resolution=info["truth_resolution"],
            dataset=None if _same_dataset(dataset, config.dataset) else dataset,
        )
        _check_identity(out_dir, {**info, "model": config.model, "flow_source": flow_source})
        results[config.model] = evaluate_source(
            model,
            variables,
            source,
            batch_size=batch_size,
            flow_source=flow_source,
            max_examples=max_examples,
            progress=True,
            truth=truth,
        )
        apply = jax.jit(functools.partial(layers.apply_model, model))
        input_keys = layers.input_keys(model)
        predict_depth = lambda batch: apply(  # noqa: E731
            variables, {key: batch[key] for key in input_keys}
        )["depth"]
        gt_pixels, seed = config.gt_pixels, config.seed
        # The step restored: the newest intact checkpoint unless one was asked for.
        info.update(
            model=config.model,
            gt_pixels=config.gt_pixels,
            flow_source=flow_source,
            step=int(restored_step),
        )
    wanted = {
        "dataset_mean": with_dataset_mean and train_source is not None,
        ORACLE: with_oracle,
        SFM: with_sfm_flow,
    }
    references = [name for name in REFERENCES if wanted[name] and name != info["model"]]
    for reference in references if jax.process_index() == 0 else []:
        fitted[reference] = _fit_reference(reference, train_source, flow_source, fitted)
        results[reference] = evaluate_predictor(
            host_predictor(reference, fitted[reference].predict),
            source,
            batch_size=batch_size,
            flow_source=flow_source,
            max_examples=max_examples,
            truth=truth,
        )
    if "dataset_mean" in results:
        info["dataset_mean_inv_depth"] = fitted["dataset_mean"].inv_depth
    if SFM in results:
        info["sfm_flow_fallback_inv_depth"] = fitted[SFM].fallback_inv_depth
        info["sfm_flow_fallback"] = (
            "the training split's mean inverse depth"
            if train_source is not None
            else "a fixed constant (no training split)"
        )
    if jax.process_index() != 0:
        return {}
    report = reports.write_report(
        out_dir,
        results,
        height=height,
        width=width,
        info=info,
        protocol_note=protocol_note,
        truth_resolution=info["truth_resolution"],
        file_resolutions=file_resolutions,
    )
    if num_figures:
        evaluated = input_pipeline.first_records(source, max_examples)
        examples = _figure_examples(evaluated, num_figures, gt_pixels, seed, flow_source, split)
        batch = {
            key: np.stack([example[key] for example in examples])
            for key, value in examples[0].items()
            if isinstance(value, np.ndarray)
        }
        batch["id"] = np.array([example["id"] for example in examples])
        # Drawn at the records' resolution, next to the records' truth.
        depth_maps = [
            metrics.resize_nearest(np.asarray(depth), height, width)
            for depth in predict_depth(batch)
        ]
        reports.render_examples(out_dir / "figures", examples, depth_maps)
    print_fn((out_dir / "table.md").read_text())
    return report
