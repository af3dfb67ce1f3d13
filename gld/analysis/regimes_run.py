"""Where a trained model beats the classical pipeline, over a whole evaluation
(`python -m experiments.regimes`): the per-pair Abs-Inv of the model and of the reference
that `experiments.evaluate` wrote, each evaluated pair's properties read from the
dataset's record (`gld.analysis.regimes`), binned, summarised and drawn.

Writes regimes.csv (one row per pair), regimes.md (per bin: pairs, mean Abs-Inv of both,
their ratio, the share of pairs the model wins) and regimes.png (the per-pair ratio
against each property). The dataset is given by the caller's `get_builder` (the data
layer, which the library does not import).
"""

from __future__ import annotations

import csv
import dataclasses
import json
from collections.abc import Callable, Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from gld import contract, input_pipeline
from gld.analysis import regimes
from gld.arguments import ArgumentError
from gld.evaluation import trained_run
from gld.runs import workdir as workdir_lib

PER_EXAMPLE_CSV = "per_example_{}.csv"
# example -> (texture kind [H, W] per pixel of view 1, an index into the names; the names)
TextureReader = Callable[[Mapping[str, Any]], tuple[np.ndarray, Sequence[str]]]


def read_per_example(path: Path, evaluate_command: str) -> dict[str, dict[str, str]]:
    """id -> row of a per-example CSV (with an abs_inv column); `evaluate_command` is the
    command that writes it, named when it is missing."""
    if not path.exists():
        raise ArgumentError(f"{path} not found: evaluate first ({evaluate_command})")
    with path.open() as file:
        rows = list(csv.DictReader(file))
    if not rows or not {"id", "abs_inv"} <= set(rows[0]):
        raise ArgumentError(f"{path} has no id and abs_inv columns (or no row)")
    return {row["id"]: row for row in rows}


def find_evaluation(
    workdir: Path, dataset: str | None = None, eval_dir: str | Path | None = None
) -> tuple[Path, str, dict]:
    """The evaluation folder of `workdir` on `dataset` (default: the workdir's own; the
    folder `experiments.evaluate` writes, or `eval_dir`), the dataset it evaluates
    ('name/config/version') and its metrics.json."""
    try:
        config = workdir_lib.load_run_config(workdir)
    except FileNotFoundError as error:
        raise ArgumentError(f"--workdir: {error}") from None
    dataset = dataset or config.dataset
    if eval_dir:
        eval_dir = Path(eval_dir)
    else:
        own = dataset.split("/")[:2] == config.dataset.split("/")[:2]
        eval_dir = trained_run.evaluation_dir(workdir, dataset=None if own else dataset)
    metrics_path = eval_dir / "metrics.json"
    if not metrics_path.exists():
        raise ArgumentError(
            f"{metrics_path} not found: evaluate {workdir} on {dataset} first "
            f"(python -m experiments.evaluate --workdir={workdir} --dataset={dataset})"
        )
    metrics = json.loads(metrics_path.read_text())
    evaluated = str(metrics.get("dataset", ""))
    if evaluated.split("/")[:2] != dataset.split("/")[:2]:
        raise ArgumentError(
            f"{eval_dir} evaluates {evaluated or 'an unnamed dataset'}, not --dataset={dataset}"
        )
    return eval_dir, evaluated, metrics


@dataclasses.dataclass(frozen=True)
class Comparison:
    """A model against a reference, pair by pair (`compare_pairs`).

    Attributes:
      rows: one per pair, sorted by id: its id, both Abs-Inv, its properties
        (`regimes.PROPERTIES`, sfm_failed; texture_kind and texture_share where the
        dataset tells) and the ratio model / reference.
      tables: property -> its bins' `regimes.BinSummary` rows.
      correlations: property -> Spearman correlation with log(model / reference).
      edges: property -> its bins' edges.
      categories: each pair's texture kind (None where the dataset cannot tell).
    """

    rows: list[dict[str, Any]]
    tables: dict[str, list[regimes.BinSummary]]
    correlations: dict[str, float]
    edges: dict[str, np.ndarray]
    categories: list[str] | None

    def draw(self, path: str | Path, *, model: str, reference: str) -> None:
        """The per-pair ratio against each property (`regimes.draw_regimes`)."""
        regimes.draw_regimes(
            path,
            {key: np.array([row[key] for row in self.rows]) for key in regimes.PROPERTIES},
            np.array([row["ratio"] for row in self.rows]),
            edges=self.edges,
            categories=self.categories,
            model=model,
            reference=reference,
        )


def compare_pairs(
    examples: Iterable[Mapping[str, Any]],
    model_abs_inv: Mapping[str, float],
    reference_abs_inv: Mapping[str, float],
    *,
    model: str,
    reference: str,
    read_texture: TextureReader | None = None,
    num_bins: int = 3,
) -> Comparison:
    """Each scored pair's properties, the per-pair ratio of the two methods' Abs-Inv, and
    their summary by property bin.

    Args:
      examples: decoded examples (`gld.contract.decode_example`, before scale
        normalisation); those whose id is not scored are skipped.
      model_abs_inv, reference_abs_inv: id -> the pair's Abs-Inv, over the same ids.
      model, reference: their names (the rows' column names).
      read_texture: the dataset's `TextureReader` (None: no texture property).
      num_bins: quantile bins per property.

    Raises:
      ValueError: the two score other pairs, a scored pair is not among the examples, or
        the texture reader refuses a pair.
    """
    if set(model_abs_inv) != set(reference_abs_inv):
        raise ValueError(f"{model} and {reference} were scored on other pairs")
    rows = []
    for example in examples:
        if example["id"] not in model_abs_inv:
            continue
        properties = regimes.pair_properties(example, regimes.sfm_flow_pose(example))
        row = {
            "id": example["id"],
            f"{model}_abs_inv": float(model_abs_inv[example["id"]]),
            f"{reference}_abs_inv": float(reference_abs_inv[example["id"]]),
            **properties,
        }
        if read_texture is not None:
            texture_kind, names = read_texture(example)
            kind, share = regimes.dominant_texture(texture_kind, example["depth_valid"], names)
            row.update(texture_kind=kind, texture_share=share)
        rows.append(row)
    missing = set(model_abs_inv) - {row["id"] for row in rows}
    if missing:
        raise ValueError(
            f"{len(missing)} scored pairs (e.g. {sorted(missing)[0]}) are not among the "
            "examples: they were scored on another dataset"
        )
    rows.sort(key=lambda row: row["id"])

    model_values = np.array([row[f"{model}_abs_inv"] for row in rows])
    reference_values = np.array([row[f"{reference}_abs_inv"] for row in rows])
    ratios = model_values / reference_values
    for row, ratio in zip(rows, ratios, strict=True):
        row["ratio"] = float(ratio)
    tables, edges, correlations = {}, {}, {}
    for key in regimes.PROPERTIES:
        values = np.array([row[key] for row in rows])
        labels, edges[key] = regimes.quantile_bins(values, num_bins)
        tables[key] = regimes.summarise_bins(labels, model_values, reference_values)
        correlations[key] = regimes.rank_correlation(values, np.log(ratios))
    categories = None
    if read_texture is not None:
        categories = [row["texture_kind"] for row in rows]
        tables[regimes.TEXTURE_PROPERTY] = regimes.summarise_bins(
            categories, model_values, reference_values
        )
    return Comparison(rows, tables, correlations, edges, categories)


def write_regimes(
    workdir: str | Path,
    output_dir: str | Path,
    *,
    get_builder: Callable[[str], Any],
    texture_reader: Callable[[Any], TextureReader | None],
    dataset: str | None = None,
    eval_dir: str | Path | None = None,
    reference: str = "sfm_flow",
    num_bins: int = 3,
    print_fn: Callable[[str], None] = print,
) -> str:
    """Compares the workdir's evaluated model with `reference`, pair by pair, by property.

    Args:
      workdir: an evaluated training workdir.
      output_dir: where regimes.csv, .md and .png go.
      get_builder: dataset name ('name/config') -> its TFDS builder, built or not.
      texture_reader: builder -> `TextureReader` of its examples, or None where the
        dataset cannot tell (`data.gld_scenes.redraw.texture_reader`).
      dataset: the evaluated dataset (default: the workdir's own).
      eval_dir: the evaluation folder (default: the one `experiments.evaluate` writes).
      reference: the method the model is compared with.
      num_bins: quantile bins per property.
      print_fn: shows a warning when sfm_flow's pose fails on other pairs than in the
        evaluation.

    Returns:
      The markdown summary (regimes.md).

    Raises:
      ArgumentError: the evaluation is missing, of another dataset or of other pairs;
        the dataset is not built, or not the one evaluated.
    """
    evaluate_command = f"python -m experiments.evaluate --workdir={workdir}" + (
        f" --dataset={dataset}" if dataset else ""
    )
    workdir = Path(workdir)
    eval_dir, evaluated, metrics = find_evaluation(workdir, dataset, eval_dir)
    model = str(metrics.get("model", "model"))
    if model == reference:
        raise ArgumentError(f"{eval_dir} evaluates {model} itself: nothing to compare")
    model_rows = read_per_example(eval_dir / PER_EXAMPLE_CSV.format(model), evaluate_command)
    reference_rows = read_per_example(
        eval_dir / PER_EXAMPLE_CSV.format(reference), evaluate_command
    )
    model_abs_inv = {key: float(row["abs_inv"]) for key, row in model_rows.items()}
    reference_abs_inv = {key: float(row["abs_inv"]) for key, row in reference_rows.items()}
    if set(model_abs_inv) != set(reference_abs_inv):
        raise ArgumentError(f"{eval_dir}: {model} and {reference} were scored on other pairs")

    name = "/".join(evaluated.split("/")[:2])
    builder = get_builder(name)
    if not builder.is_prepared():
        raise ArgumentError(
            f"{evaluated} is not built under {builder.data_dir}: build it first "
            f"(python -m data.build --dataset={name})"
        )
    if builder.info.full_name != evaluated:
        raise ArgumentError(f"{eval_dir} evaluates {evaluated}; {builder.info.full_name} is built")
    split = str(metrics.get("split", "test"))
    flow_source = str(metrics.get("flow_source", "estimated"))
    source = builder.as_data_source(split, decoders=input_pipeline.source_decoders())

    examples = (
        contract.decode_example(
            source[index], flow_source=flow_source, where=f"{name} {split}[{index}]"
        )
        for index in tqdm(range(len(source)), desc="pairs", unit="pair")
    )
    try:
        compared = compare_pairs(
            examples,
            model_abs_inv,
            reference_abs_inv,
            model=model,
            reference=reference,
            read_texture=texture_reader(builder),
            num_bins=num_bins,
        )
    except ValueError as error:
        raise ArgumentError(f"{eval_dir}: {error}") from None
    rows, tables, correlations = compared.rows, compared.tables, compared.correlations
    failed = int(sum(row["sfm_failed"] for row in rows))
    if reference == "sfm_flow" and "failed" in next(iter(reference_rows.values())):
        # The pose scored here is estimated again: it must fail where the evaluation's did.
        disagree = [
            row["id"]
            for row in rows
            if float(reference_rows[row["id"]]["failed"]) != row["sfm_failed"]
        ]
        if disagree:
            print_fn(
                f"warning: sfm_flow's pose failed here and in the evaluation on other pairs "
                f"({len(disagree)}, e.g. {disagree[0]}): its settings may differ"
            )
    title = (
        f"# {model} against {reference}, pair by pair: {evaluated} {split}, {len(rows)} "
        f"pairs, {flow_source} flow ({eval_dir}); sfm_flow's pose failed on {failed}"
    )
    summary = regimes.markdown_summary(
        tables, model=model, reference=reference, correlations=correlations, title=title
    )

    output_dir = Path(output_dir)
    output_dir.mkdir(parents=True, exist_ok=True)
    with (output_dir / "regimes.csv").open("w", newline="") as file:
        writer = csv.DictWriter(file, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    (output_dir / "regimes.md").write_text(summary)
    compared.draw(output_dir / "regimes.png", model=model, reference=reference)
    return summary
