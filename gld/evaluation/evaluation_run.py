"""One evaluation as `python -m experiments.evaluate` runs it: a trained workdir, a
classical method or stored depth maps on a dataset's split, scored against the records'
ground truth or DeMoN's files, with the references the dataset allows (the dataset mean
only with a training split), then `trained_run.evaluate_workdir`.

A DeMoN dataset (`demon/*`) is scored by DeMoN's protocol unless told otherwise: against
its files' depth (`truth_resolution="file"`, the default there), in the records' order,
which its builder made DeMoN's; the report names the records' protocol (their build
options: WebP decoder, depth resampling, order). Without the files the evaluation is
refused, naming both ways on (`--manual_dir`, or `--truth_resolution=record`): a
number at the records' resolution is not DeMoN's (on 640x480 files, Abs-Inv can differ
by most of its value) and must be asked for. The end of a training run is the exception
(`rescore_command`): it is scored at the records' resolution rather than lost, saying so
in one line and in the report's stamp, with the command that scores it by DeMoN's
protocol once the files are back. Other datasets are scored at the records' resolution.
`open_truth` chooses and opens the truth for any evaluation of a split (the comparison
of methods too).

The dataset and DeMoN's files are opened by the caller's `prepare_dataset` and
`open_file_truth` (the data layer, which the library does not import).
"""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path
from typing import Any

from gld import input_pipeline
from gld.arguments import ArgumentError
from gld.evaluation import stored_predictions, trained_run
from gld.evaluation.evaluate import Truth
from gld.runs import workdir as workdir_lib

# The build options that make a DeMoN dataset's records protocol, named in the report.
RECORDS_PROTOCOL = ("image_decoder", "depth_resampling", "order")


def default_truth_resolution(dataset: str) -> str:
    """Where a dataset's ground truth is scored by default: DeMoN's files for `demon/*`
    (DeMoN's protocol), the records for the others."""
    return "file" if dataset.startswith("demon/") else "record"


def records_protocol(builder: Any, split: str) -> dict[str, Any]:
    """The `RECORDS_PROTOCOL` options `split` was built with, from the builder's
    `metadata["build_options"]` (empty for a dataset that records none of them)."""
    metadata = getattr(builder.info, "metadata", None) or {}
    options = metadata.get("build_options", {}).get(split, {})
    return {key: options[key] for key in RECORDS_PROTOCOL if key in options}


def resolve_truth_resolution(dataset: str, truth_resolution: str | None) -> str:
    """`truth_resolution`, or the dataset's default (`default_truth_resolution`).

    Raises:
      ArgumentError: "file" for another dataset than demon/*.
    """
    resolved = truth_resolution or default_truth_resolution(dataset)
    if resolved == "file" and not dataset.startswith("demon/"):
        raise ArgumentError(
            f"--truth_resolution=file reads the ground truth from DeMoN's HDF5 files "
            f"by example id; {dataset} is not a demon/* dataset, its records are its "
            f"only ground truth (use --truth_resolution=record)"
        )
    return resolved


def _one_line(error: Exception) -> str:
    """The first line of an error's message (a file truth's check names every example
    on lines of their own)."""
    return str(error).splitlines()[0].rstrip(":") if str(error) else type(error).__name__


def open_truth(
    builder: Any,
    split: str,
    source,
    *,
    open_file_truth: Callable[[Any, str, str | None], Truth],
    truth_resolution: str | None = None,
    manual_dir: str | None = None,
    max_examples: int = 0,
    rescore_command: str | None = None,
    print_fn: Callable[[str], None] = print,
) -> tuple[Truth | None, str]:
    """The ground truth the first `max_examples` records of `source` (`split` of the built
    dataset `builder`) are scored against.

    Args:
      open_file_truth, manual_dir: as `evaluate_split` takes them.
      truth_resolution: "record", "file" or None: `default_truth_resolution`.
      rescore_command: given, a demon/* dataset whose files are not at hand by default is
        scored at the records' resolution instead of refused (the end of a training run,
        which must not be lost): one line says so and names this command, which scores it
        by DeMoN's protocol once the files are back.

    Returns:
      (truth, stamp note): truth None for the records' resolution, else DeMoN's files,
      checked to serve every example (close it after use); the note, for the protocol
      stamp, says that the files were not at hand ("" unless scored without them).

    Raises:
      ArgumentError: "file" for another dataset than demon/*; the files not at hand (or
        not those the split was built from) when asked for by name, or by default
        without `rescore_command` (naming --manual_dir and --truth_resolution=record).
    """
    dataset = builder.info.full_name
    if resolve_truth_resolution(dataset, truth_resolution) == "record":
        return None, ""
    try:
        truth = open_file_truth(builder, split, manual_dir)
        try:
            truth.check(
                stored_predictions.record_ids_and_baselines(
                    input_pipeline.first_records(source, max_examples)
                )
            )
        except BaseException:
            truth.close()
            raise
        return truth, ""
    except (FileNotFoundError, ValueError) as error:
        if truth_resolution:
            raise ArgumentError(f"--truth_resolution=file: {error}") from None
        height, width = (int(size) for size in builder.info.features["depth1"].shape)
        if rescore_command is None:
            raise ArgumentError(
                f"{dataset} is scored as DeMoN scores it, against the depth of the files "
                f"its {split} split was built from (--truth_resolution=file, the default "
                f"for demon/* datasets), and they are not at hand: {error}. Give "
                f"--manual_dir=<the folder of those files>, or --truth_resolution=record to "
                f"score at the records' {width}x{height} (not DeMoN's protocol)"
            ) from None
        print_fn(
            f"{dataset} {split} split: scored at the records' {width}x{height}, not by "
            f"DeMoN's protocol (the depth of its files): the files it was built from are not "
            f"at hand ({_one_line(error)}); to score it by DeMoN's protocol: {rescore_command}"
        )
        note = (
            f"not DeMoN's protocol: the DeMoN files of the {split} split were not at hand "
            f"(score by it: {rescore_command})"
        )
        return None, note


def final_evaluation_of(workdir: str | Path, dataset: str, step: int) -> Path | None:
    """The folder holding the test split's whole evaluation of the workdir's model at
    `step` by the dataset's default protocol (what a trainer's final evaluation writes
    when it can), or None when there is none. (A DeMoN run evaluated at the records'
    resolution for want of its files is not it: a relaunch with the files evaluates.)"""
    out_dir = trained_run.evaluation_dir(
        workdir, truth_resolution=default_truth_resolution(dataset)
    )
    try:
        report = json.loads((out_dir / "metrics.json").read_text())
    except (OSError, ValueError):
        return None
    return out_dir if report.get("step") == step and report.get("split") == "test" else None


def evaluate_split(
    workdir: str | Path,
    *,
    prepare_dataset: Callable[[str], Any],
    open_file_truth: Callable[[Any, str, str | None], Truth],
    dataset: str | None = None,
    method: str | None = None,
    predictions: stored_predictions.StoredPredictions | None = None,
    truth_resolution: str | None = None,
    manual_dir: str | None = None,
    split: str = "test",
    batch_size: int = 16,
    num_figures: int = 8,
    max_examples: int = 0,
    with_dataset_mean: bool = True,
    with_oracle: bool = True,
    with_sfm_flow: bool = True,
    step: int | None = None,
    flow_source: str | None = None,
    rescore_command: str | None = None,
    print_fn: Callable[[str], None] = print,
) -> dict[str, Any]:
    """Evaluates the workdir's model, or the classical `method`, or `predictions`, on
    `split` of `dataset` (default: the workdir's; needed with a method or predictions).

    Args:
      prepare_dataset: dataset name ('name/config') -> its TFDS builder, built on first
        use.
      open_file_truth: (builder, split, manual_dir or None) -> the ground truth of the
        split's DeMoN files, by example id (`data.demon.file_truth.for_split`: in
        `manual_dir`, else where the build recorded them), for
        `truth_resolution="file"`; raises FileNotFoundError or ValueError when the
        files are not those the split was built from.
      truth_resolution: "record" (the records' resolution), "file" (DeMoN's files;
        demon/* datasets only) or None: `default_truth_resolution`.
      rescore_command: given, a demon/* dataset whose files are not at hand is scored at
        the records' resolution rather than refused (`open_truth`).
      The others: `trained_run.evaluate_workdir`'s; `print_fn` also says which
        references a dataset without a training split goes without.

    Returns:
      `trained_run.evaluate_workdir`'s report (what metrics.json holds), with the
      records' protocol (`records_protocol`) where the dataset records one.

    Raises:
      ArgumentError: no dataset for a method or predictions; the file resolution for
        another dataset than demon/*, or without the files the split was built from
        (`open_truth`); a split the dataset lacks; the dataset mean without a training
        split.
    """
    if method or predictions:
        if not dataset:
            raise ArgumentError("--dataset is needed with --method or --predictions")
    else:
        dataset = dataset or workdir_lib.load_run_config(workdir).dataset
    resolve_truth_resolution(dataset, truth_resolution)  # before the dataset is built
    builder = prepare_dataset(dataset)
    height, width = (int(size) for size in builder.info.features["depth1"].shape)
    splits = builder.info.splits
    if split not in splits:
        raise ArgumentError(f"--split={split}: {builder.info.full_name} has only {sorted(splits)}")
    if method == "dataset_mean" and "train" not in splits:
        raise ArgumentError(
            f"--method=dataset_mean is fitted on the train split, which "
            f"{builder.info.full_name} lacks"
        )
    decoders = input_pipeline.source_decoders()
    source = builder.as_data_source(split, decoders=decoders)
    train_source = None
    if "train" in splits:
        train_source = builder.as_data_source("train", decoders=decoders)
    else:
        if with_dataset_mean:
            print_fn(f"{builder.info.full_name} has no training split: no dataset-mean row")
        if with_sfm_flow or method == "sfm_flow":
            print_fn(
                f"{builder.info.full_name} has no training split: sfm_flow's failed pairs "
                f"are predicted as a fixed inverse depth, not the training mean"
            )
    truth, protocol_note = open_truth(
        builder,
        split,
        source,
        open_file_truth=open_file_truth,
        truth_resolution=truth_resolution,
        manual_dir=manual_dir,
        max_examples=max_examples,
        rescore_command=rescore_command,
        print_fn=print_fn,
    )
    try:
        return trained_run.evaluate_workdir(
            workdir,
            source,
            train_source=train_source,
            dataset=builder.info.full_name,
            height=height,
            width=width,
            split=split,
            print_fn=print_fn,
            num_figures=num_figures,
            with_dataset_mean=with_dataset_mean,
            with_oracle=with_oracle,
            with_sfm_flow=with_sfm_flow,
            batch_size=batch_size,
            max_examples=max_examples,
            step=step,
            classical_method=method,
            predictions=predictions,
            flow_source=flow_source,
            truth=truth,
            records_protocol=records_protocol(builder, split),
            protocol_note=protocol_note,
        )
    finally:
        if truth is not None:
            truth.close()
