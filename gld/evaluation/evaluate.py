"""Evaluation: one loop over a split for learned models and host-side methods alike.

`evaluate_source` runs a learned model (jit, sharded over a mesh, exact means over
padded batches); `evaluate_predictor` runs any host-side `predict(batch) -> {"depth",
...}` (the classical baselines and references). Both go through `evaluate_batches`, the
one loop, and score with `score_batch`, the one rule for which rows count. Training's
periodic evaluation, `experiments.evaluate`, `experiments.compare` and
`experiments.inspect_filters` read splits through `split_batches`. A trained
workdir is evaluated with its references by `gld.evaluation.trained_run`.

The ground truth is the records' (`score_batch`) unless a `Truth` is given: then each
example is scored against the truth it looks up by id, at that truth's resolution, the
prediction resized to it by centre-aligned nearest neighbour (`score_against_truth`;
DeMoN's evaluation at its files' resolution, `data.demon.file_truth`).
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Iterator, Sequence
from typing import Any, Protocol

import flax.linen as nn
import jax
import numpy as np
from jax.sharding import Mesh

from gld import input_pipeline, sharding
from gld.evaluation import metrics
from gld.models import layers

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
        ||t||; raises naming every example it cannot serve, before anything is scored.
        Checking the examples checked last again costs nothing (the opener and the
        scorer both check)."""

    def shapes(self) -> dict[str, tuple[int, int]]:
        """id -> (height, width) of its truth, for every checked example."""

    def maps(self, ids: Sequence[str]) -> list[tuple[np.ndarray, np.ndarray]]:
        """(depth [h, w] float32 scaled so that ||t|| = 1, 0 where invalid; valid [h, w]
        bool) of each id, as `contract.prepare_example` makes a record's."""

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
