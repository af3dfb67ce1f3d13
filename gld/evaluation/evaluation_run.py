"""One evaluation as `python -m experiments.evaluate` runs it: a trained workdir, a
classical method or stored depth maps on a dataset's split, scored against the records'
ground truth or DeMoN's files, with the references the dataset allows (the dataset mean
only with a training split), then `trained_run.evaluate_workdir`.

The dataset and DeMoN's files are opened by the caller's `prepare_dataset` and
`open_file_truth` (the data layer, which the library does not import).
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

from gld import input_pipeline
from gld.arguments import ArgumentError
from gld.evaluation import stored_predictions, trained_run
from gld.evaluation.evaluate import Truth
from gld.runs import workdir as workdir_lib


def evaluate_split(
    workdir: str | Path,
    *,
    prepare_dataset: Callable[[str], Any],
    open_file_truth: Callable[[str], Truth],
    dataset: str | None = None,
    method: str | None = None,
    predictions: stored_predictions.StoredPredictions | None = None,
    truth_resolution: str = "record",
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
    print_fn: Callable[[str], None] = print,
) -> dict[str, Any]:
    """Evaluates the workdir's model, or the classical `method`, or `predictions`, on
    `split` of `dataset` (default: the workdir's; needed with a method or predictions).

    Args:
      prepare_dataset: dataset name ('name/config') -> its TFDS builder, built on first
        use.
      open_file_truth: a folder of DeMoN's files -> the ground truth they hold, by
        example id (`data.demon.file_truth.FileTruth`), for `truth_resolution="file"`.
      truth_resolution: "record" (the records' resolution) or "file" (DeMoN's files in
        `manual_dir`; demon/* datasets only).
      The others: `trained_run.evaluate_workdir`'s; `print_fn` also says which
        references a dataset without a training split goes without.

    Returns:
      `trained_run.evaluate_workdir`'s report (what metrics.json holds).

    Raises:
      ArgumentError: no dataset for a method or predictions; the file resolution for
        another dataset than demon/*, or without DeMoN's files; a split the dataset
        lacks; the dataset mean without a training split.
    """
    if method or predictions:
        if not dataset:
            raise ArgumentError("--dataset is needed with --method or --predictions")
    else:
        dataset = dataset or workdir_lib.load_run_config(workdir).dataset
    truth = None
    if truth_resolution == "file":
        if not dataset.startswith("demon/"):
            raise ArgumentError(
                f"--truth_resolution=file reads the ground truth from DeMoN's HDF5 files "
                f"by example id; {dataset} is not a demon/* dataset, its records are its "
                f"only ground truth (use --truth_resolution=record)"
            )
        if not manual_dir:
            raise ArgumentError(
                "--truth_resolution=file needs --manual_dir: the folder of the DeMoN "
                "files the dataset was built from"
            )
        try:
            truth = open_file_truth(manual_dir)
        except FileNotFoundError as error:
            raise ArgumentError(f"--manual_dir: {error}") from None
    builder = prepare_dataset(dataset)
    height, width = (int(size) for size in builder.info.features["depth1"].shape)
    splits = builder.info.splits
    if split not in splits:
        raise ArgumentError(f"--split={split}: {builder.info.full_name} has only {sorted(splits)}")
    decoders = input_pipeline.source_decoders()
    train_source = None
    if "train" in splits:
        train_source = builder.as_data_source("train", decoders=decoders)
    elif method == "dataset_mean":
        raise ArgumentError(
            f"--method=dataset_mean is fitted on the train split, which "
            f"{builder.info.full_name} lacks"
        )
    else:
        if with_dataset_mean:
            print_fn(f"{builder.info.full_name} has no training split: no dataset-mean row")
        if with_sfm_flow or method == "sfm_flow":
            print_fn(
                f"{builder.info.full_name} has no training split: sfm_flow's failed pairs "
                f"are predicted as a fixed inverse depth, not the training mean"
            )
    report = trained_run.evaluate_workdir(
        workdir,
        builder.as_data_source(split, decoders=decoders),
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
    )
    if truth is not None:
        truth.close()
    return report
