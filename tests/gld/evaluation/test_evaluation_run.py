"""One evaluation as experiments.evaluate runs it (gld/evaluation/evaluation_run.py): the
dataset, the truth's resolution and the split are checked, by their flags' names, before
anything is evaluated or written; a dataset without a training split goes without the
dataset mean. The evaluation itself: tests/gld/evaluation/test_evaluate.py and the
launcher's tests (tests/experiments/test_train_launcher.py)."""

from types import SimpleNamespace

import pytest
from conftest import tiny_train_config

from gld.arguments import ArgumentError
from gld.evaluation import evaluation_run
from gld.runs import workdir as workdir_lib


def _builder(name, splits=("train", "test")):
    info = SimpleNamespace(
        full_name=f"{name}/1.0.0",
        splits=dict.fromkeys(splits),
        features={"depth1": SimpleNamespace(shape=(48, 64))},
    )
    return SimpleNamespace(info=info)


def _no_truth(folder):
    raise AssertionError("opened")


def _refused(workdir, message, *, builder=None, open_file_truth=_no_truth, **arguments):
    def prepare_dataset(name):
        if builder is None:
            raise AssertionError("prepared")
        return builder

    with pytest.raises(ArgumentError, match=message):
        evaluation_run.evaluate_split(
            workdir,
            prepare_dataset=prepare_dataset,
            open_file_truth=open_file_truth,
            **arguments,
        )
    assert not workdir.exists()


def test_the_dataset_and_the_truths_resolution_are_checked_first(tmp_path):
    workdir = tmp_path / "run"
    _refused(workdir, "--dataset is needed with --method or --predictions", method="sfm_flow")
    _refused(
        workdir,
        "--truth_resolution=file reads .*; gld_scenes/tiny is not a demon/\\* dataset",
        method="sfm_flow",
        dataset="gld_scenes/tiny",
        truth_resolution="file",
    )
    _refused(
        workdir,
        "--truth_resolution=file needs --manual_dir",
        method="sfm_flow",
        dataset="demon/sun3d",
        truth_resolution="file",
    )

    def missing(folder):
        raise FileNotFoundError(f"no DeMoN files in {folder}")

    _refused(
        workdir,
        "--manual_dir: no DeMoN files in nowhere",
        method="sfm_flow",
        dataset="demon/sun3d",
        truth_resolution="file",
        manual_dir="nowhere",
        open_file_truth=missing,
    )


def test_the_split_and_the_dataset_mean_need_the_dataset_to_have_them(tmp_path):
    trained = tmp_path / "trained"
    workdir_lib.write_run_config(trained, tiny_train_config())
    with pytest.raises(ArgumentError, match=r"--split=val: gld_scenes/tiny/1.0.0 has only \["):
        evaluation_run.evaluate_split(
            trained,
            prepare_dataset=_builder,  # the workdir's dataset, by default
            open_file_truth=_no_truth,
            split="val",
        )
    _refused(
        tmp_path / "mean",
        "--method=dataset_mean is fitted on the train split, which demon/sun3d/1.0.0 lacks",
        builder=_builder("demon/sun3d", splits=("test",)),
        method="dataset_mean",
        dataset="demon/sun3d",
    )
