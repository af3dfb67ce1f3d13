r"""Where a trained model beats the classical pipeline, pair by pair, and why.

    python -m experiments.regimes --workdir=runs/v2/main_s0 --output_dir=out/regimes
    python -m experiments.regimes --workdir=runs/v2/main_s0 \
        --dataset=gld_scenes/small_untextured --output_dir=out/regimes_untextured

Reads the workdir's evaluation on --dataset (default: the workdir's own; the folder
`python -m experiments.evaluate` writes, e.g. <workdir>/eval or
<workdir>/eval_gld_scenes-small_untextured, or --eval_dir): the per-pair Abs-Inv of the
model (per_example_<model>.csv) and of sfm_flow, the classical pipeline on the same flow
(per_example_sfm_flow.csv). For each evaluated pair it computes, from the dataset's
record (`gld.analysis.regimes`): the baseline (raw ||t||), the rotation share of the true flow,
the flow's end-point error, sfm_flow's pose errors (its pose estimated again from the
same flow) and, for gld_scenes, the texture kind covering most of view 1 (the pair's
scene drawn again from its seed, as the builder draws it, and checked against the
record's depth). Each property is binned in --num_bins quantile bins.

Writes to --output_dir: regimes.csv (one row per pair), regimes.md (per bin: pairs,
mean Abs-Inv of both, their ratio, the share of pairs the model wins; printed too) and
regimes.png (the per-pair ratio against each property). The dataset must be built.
"""

from __future__ import annotations

import csv
import json
from pathlib import Path

from absl import app, flags

from experiments import common

FLAGS = flags.FLAGS

flags.DEFINE_string("workdir", None, "Evaluated training workdir.", required=True)
flags.DEFINE_string(
    "eval_dir",
    None,
    "The evaluation folder to read (default: the one experiments.evaluate writes for "
    "--dataset in --workdir).",
)
flags.DEFINE_string("output_dir", None, "Where regimes.csv, .md and .png go.", required=True)
flags.DEFINE_string("reference", "sfm_flow", "The method the model is compared with.")
flags.DEFINE_integer("num_bins", 3, "Quantile bins per property (3: terciles).", lower_bound=1)
common.define_data_flags(default_dataset=None)

PER_EXAMPLE_CSV = "per_example_{}.csv"


def _read_per_example(path: Path) -> dict[str, dict[str, str]]:
    """id -> row of a per-example CSV (with an abs_inv column)."""
    if not path.exists():
        raise app.UsageError(
            f"{path} not found: evaluate first (python -m experiments.evaluate "
            f"--workdir={FLAGS.workdir}{' --dataset=' + FLAGS.dataset if FLAGS.dataset else ''})"
        )
    with path.open() as file:
        rows = list(csv.DictReader(file))
    if not rows or not {"id", "abs_inv"} <= set(rows[0]):
        raise app.UsageError(f"{path} has no id and abs_inv columns (or no row)")
    return {row["id"]: row for row in rows}


def _evaluation(workdir: Path) -> tuple[Path, str, dict]:
    """The evaluation folder, the dataset ('name/config') and its metrics.json."""
    from gld.evaluation import trained_run
    from gld.runs import workdir as workdir_lib

    try:
        config = workdir_lib.load_run_config(workdir)
    except FileNotFoundError as error:
        raise app.UsageError(f"--workdir: {error}") from None
    dataset = FLAGS.dataset or config.dataset
    if FLAGS.eval_dir:
        eval_dir = Path(FLAGS.eval_dir)
    else:
        own = dataset.split("/")[:2] == config.dataset.split("/")[:2]
        eval_dir = trained_run.evaluation_dir(workdir, dataset=None if own else dataset)
    metrics_path = eval_dir / "metrics.json"
    if not metrics_path.exists():
        raise app.UsageError(
            f"{metrics_path} not found: evaluate {workdir} on {dataset} first "
            f"(python -m experiments.evaluate --workdir={workdir} --dataset={dataset})"
        )
    metrics = json.loads(metrics_path.read_text())
    evaluated = str(metrics.get("dataset", ""))
    if evaluated.split("/")[:2] != dataset.split("/")[:2]:
        raise app.UsageError(
            f"{eval_dir} evaluates {evaluated or 'an unnamed dataset'}, not --dataset={dataset}"
        )
    return eval_dir, evaluated, metrics


def _texture_reader(builder):
    """For gld_scenes: example -> (dominant kind, share) from the pair's scene drawn again
    (`data.gld_scenes`: an example is a pure function of its config's seed, split and
    index); None for other datasets."""
    import numpy as np

    if not builder.name.startswith("gld_scenes"):
        return None
    from data.gld_scenes import raycast, renderer, scenes
    from gld.analysis import regimes

    config = builder.builder_config
    settings = config.scene_settings()

    def read(example) -> tuple[str, float]:
        _, _, split, index = example["id"].split("/")
        rng = renderer.example_rng(config.seed, split, int(index))
        # `renderer.render_pair` draws view 1 with this call before anything else.
        scene, _, _, _, depth1, surface1 = scenes.sample_pair(rng, settings)
        stored = example["depth"]
        if not np.array_equal(np.where(example["depth_valid"], depth1, 0.0), stored):
            raise ValueError(
                f"{example['id']}: the scene drawn again from its seed does not give the "
                "record's depth; the dataset was built by other code than this one"
            )
        return regimes.dominant_texture(
            raycast.texture_kinds(scene, surface1), example["depth_valid"], raycast.TEXTURES
        )

    return read


def main(argv):
    del argv
    common.initialise()
    import numpy as np
    from tqdm import tqdm

    import data
    from gld import contract
    from gld.analysis import regimes

    workdir = Path(FLAGS.workdir)
    eval_dir, evaluated, metrics = _evaluation(workdir)
    model = str(metrics.get("model", "model"))
    reference = FLAGS.reference
    if model == reference:
        raise app.UsageError(f"{eval_dir} evaluates {model} itself: nothing to compare")
    model_rows = _read_per_example(eval_dir / PER_EXAMPLE_CSV.format(model))
    reference_rows = _read_per_example(eval_dir / PER_EXAMPLE_CSV.format(reference))
    model_abs_inv = {key: float(row["abs_inv"]) for key, row in model_rows.items()}
    reference_abs_inv = {key: float(row["abs_inv"]) for key, row in reference_rows.items()}
    if set(model_abs_inv) != set(reference_abs_inv):
        raise app.UsageError(f"{eval_dir}: {model} and {reference} were scored on other pairs")

    name = "/".join(evaluated.split("/")[:2])
    builder = data.get_builder(name, FLAGS.data_dir)
    if not builder.is_prepared():
        raise app.UsageError(
            f"{evaluated} is not built under {builder.data_dir}: build it first "
            f"(python -m data.build --dataset={name})"
        )
    if builder.info.full_name != evaluated:
        raise app.UsageError(f"{eval_dir} evaluates {evaluated}; {builder.info.full_name} is built")
    split = str(metrics.get("split", "test"))
    flow_source = str(metrics.get("flow_source", "estimated"))
    source = common.data_source(builder, split)
    read_texture = _texture_reader(builder)

    rows = []
    for index in tqdm(range(len(source)), desc="pairs", unit="pair"):
        example = contract.decode_example(
            source[index], flow_source=flow_source, where=f"{name} {split}[{index}]"
        )
        if example["id"] not in model_abs_inv:
            continue
        properties = regimes.pair_properties(example, regimes.sfm_flow_pose(example))
        row = {
            "id": example["id"],
            f"{model}_abs_inv": model_abs_inv[example["id"]],
            f"{reference}_abs_inv": reference_abs_inv[example["id"]],
            **properties,
        }
        if read_texture is not None:
            try:
                kind, share = read_texture(example)
            except ValueError as error:
                raise app.UsageError(str(error)) from None
            row.update(texture_kind=kind, texture_share=share)
        rows.append(row)
    missing = set(model_abs_inv) - {row["id"] for row in rows}
    if missing:
        raise app.UsageError(
            f"{len(missing)} evaluated pairs (e.g. {sorted(missing)[0]}) are not in "
            f"{evaluated} {split}: the evaluation is of another dataset"
        )
    rows.sort(key=lambda row: row["id"])

    model_values = np.array([row[f"{model}_abs_inv"] for row in rows])
    reference_values = np.array([row[f"{reference}_abs_inv"] for row in rows])
    ratios = model_values / reference_values
    for row, ratio in zip(rows, ratios, strict=True):
        row["ratio"] = float(ratio)
    properties = {key: np.array([row[key] for row in rows]) for key in regimes.PROPERTIES}
    tables, edges, correlations = {}, {}, {}
    for key, values in properties.items():
        labels, edges[key] = regimes.quantile_bins(values, FLAGS.num_bins)
        tables[key] = regimes.summarise_bins(labels, model_values, reference_values)
        correlations[key] = regimes.rank_correlation(values, np.log(ratios))
    categories = None
    if read_texture is not None:
        categories = [row["texture_kind"] for row in rows]
        tables[regimes.TEXTURE_PROPERTY] = regimes.summarise_bins(
            categories, model_values, reference_values
        )
    failed = int(sum(row["sfm_failed"] for row in rows))
    if reference == "sfm_flow" and "failed" in next(iter(reference_rows.values())):
        # The pose scored here is estimated again: it must fail where the evaluation's did.
        disagree = [
            row["id"]
            for row in rows
            if float(reference_rows[row["id"]]["failed"]) != row["sfm_failed"]
        ]
        if disagree:
            print(
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

    output_dir = Path(FLAGS.output_dir)
    output_dir.mkdir(parents=True, exist_ok=True)
    with (output_dir / "regimes.csv").open("w", newline="") as file:
        writer = csv.DictWriter(file, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    (output_dir / "regimes.md").write_text(summary)
    regimes.draw_regimes(
        output_dir / "regimes.png",
        properties,
        ratios,
        edges=edges,
        categories=categories,
        model=model,
        reference=reference,
    )
    print(summary)
    print(f"wrote {output_dir}/regimes.csv, regimes.md, regimes.png")


if __name__ == "__main__":
    app.run(main)
