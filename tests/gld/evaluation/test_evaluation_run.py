"""One evaluation as experiments.evaluate runs it (gld/evaluation/evaluation_run.py): the
dataset, the truth's resolution and the split are checked, by their flags' names, before
anything is evaluated or written; a dataset without a training split goes without the
dataset mean. The evaluation itself: tests/gld/evaluation/test_evaluate.py and the
launcher's tests (tests/experiments/test_train_launcher.py)."""

import json
from pathlib import Path
from types import SimpleNamespace

import pytest
from conftest import tiny_train_config

from gld.arguments import ArgumentError
from gld.evaluation import evaluation_run
from gld.runs import workdir as workdir_lib


def _builder(name, splits=("train", "test"), source=None):
    """A built dataset's stand-in: its info, and `source` as every split's records."""
    info = SimpleNamespace(
        full_name=f"{name}/1.0.0",
        splits=dict.fromkeys(splits),
        features={"depth1": SimpleNamespace(shape=(48, 64))},
    )
    return SimpleNamespace(info=info, as_data_source=lambda split, decoders=None: source)


def _no_truth(builder, split, manual_dir):
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

    def missing(builder, split, manual_dir):
        raise FileNotFoundError(f"no DeMoN files in {manual_dir}")

    _refused(
        workdir,
        "--truth_resolution=file: no DeMoN files in nowhere",
        builder=_builder("demon/sun3d"),
        method="sfm_flow",
        dataset="demon/sun3d",
        truth_resolution="file",
        manual_dir="nowhere",
        open_file_truth=missing,
    )


def test_demon_datasets_are_scored_at_their_files_resolution_by_default():
    assert evaluation_run.default_truth_resolution("demon/sun3d") == "file"
    assert evaluation_run.default_truth_resolution("demon/custom") == "file"
    assert evaluation_run.default_truth_resolution("gld_scenes/tiny") == "record"


def test_without_the_files_a_demon_dataset_is_refused_naming_both_ways_on(tmp_path):
    opened = []

    def missing(builder, split, manual_dir):
        opened.append((builder.info.full_name, split, manual_dir))
        raise FileNotFoundError("sun3d_test.h5 not in /data/demon")

    _refused(
        tmp_path / "run",
        r"demon/sun3d/1.0.0 is scored as DeMoN scores it, against the depth of the files its "
        r"test split was built from \(--truth_resolution=file, the default for demon/\* "
        r"datasets\), and they are not at hand: sun3d_test.h5 not in /data/demon. Give "
        r"--manual_dir=<the folder of those files>, or --truth_resolution=record to score "
        r"at the records' 64x48 \(not DeMoN's protocol\)",
        builder=_builder("demon/sun3d"),
        method="sfm_flow",
        dataset="demon/sun3d",
        open_file_truth=missing,
    )
    assert opened == [("demon/sun3d/1.0.0", "test", None)]


def test_the_records_protocol_is_read_from_the_build_options():
    builder = _builder("demon/sun3d")
    options = {"image_decoder": "demon", "depth_resampling": "demon", "order": "demon"}
    builder.info.metadata = {"build_options": {"test": {**options, "flow_estimator": "dis"}}}
    assert evaluation_run.records_protocol(builder, "test") == options
    assert evaluation_run.records_protocol(builder, "train") == {}
    assert evaluation_run.records_protocol(_builder("gld_scenes/tiny"), "test") == {}


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


DEMON_PROTOCOL = {"image_decoder": "demon", "depth_resampling": "demon", "order": "demon"}
RESCORE = "python -m experiments.evaluate --workdir=runs/x --manual_dir=<the folder>"


def _demon_builder(tiny_scenes):
    """demon/sun3d's stand-in: gld_scenes/tiny's records, DeMoN's records protocol."""
    builder = _builder("demon/sun3d", source=tiny_scenes.as_data_source("test"))
    builder.info.metadata = {"build_options": {"test": {**DEMON_PROTOCOL, "flow": "dis"}}}
    return builder


class _DamagedTruth:
    """DeMoN files that open but cannot serve the examples (their check fails)."""

    closed = False

    def check(self, examples):
        raise ValueError(f"cannot be read for {len(list(examples))} example(s):\n  a: gone")

    def close(self):
        self.closed = True


def _oracle(workdir, builder, open_file_truth, **arguments):
    printed = []
    report = evaluation_run.evaluate_split(
        workdir,
        prepare_dataset=lambda name: builder,
        open_file_truth=open_file_truth,
        dataset="demon/sun3d",
        method="oracle_pair_median",
        max_examples=4,
        num_figures=0,
        with_sfm_flow=False,
        print_fn=printed.append,
        **arguments,
    )
    return report, printed


@pytest.mark.parametrize("problem", ["missing", "damaged"])
def test_the_end_of_a_training_run_without_the_files_is_scored_at_the_records_and_says_so(
    tiny_scenes, tmp_path, problem
):
    damaged = _DamagedTruth()

    def open_file_truth(builder, split, manual_dir):
        if problem == "missing":
            raise FileNotFoundError("sun3d_test.h5 not in /data/demon")
        return damaged

    workdir = tmp_path / "run"
    report, printed = _oracle(
        workdir, _demon_builder(tiny_scenes), open_file_truth, rescore_command=RESCORE
    )
    # One line, before the table: the records' resolution, not DeMoN's protocol, and how
    # to score it by DeMoN's protocol.
    (line,) = [text for text in printed if "not by DeMoN's protocol" in text]
    assert "\n" not in line and printed.index(line) == 0
    reason = "sun3d_test.h5 not in /data/demon" if problem == "missing" else "cannot be read"
    assert line == (
        f"demon/sun3d/1.0.0 test split: scored at the records' 64x48, not by DeMoN's protocol "
        f"(the depth of its files): the files it was built from are not at hand "
        f"({reason}{' for 4 example(s)' if problem == 'damaged' else ''}); to score it by "
        f"DeMoN's protocol: {RESCORE}"
    )
    assert damaged.closed == (problem == "damaged")
    # The report says the same, once: at the records' resolution, stamped as not DeMoN's
    # protocol, with the records' protocol.
    assert report["truth_resolution"] == "record" and "truth_resolutions" not in report
    assert report["records_protocol"] == DEMON_PROTOCOL
    assert report["methods"]["oracle_pair_median"]["abs_inv"]["count"] == 4
    stamp = report["protocol"]
    assert "ground truth at the records' resolution, 64x48 px" in stamp
    assert stamp.endswith(
        "; not DeMoN's protocol: the DeMoN files of the test split were not at hand (score "
        f"by it: {RESCORE}); records built with image_decoder=demon, depth_resampling=demon; "
        "evaluated in the records' stored order, order=demon (DeMoN's reader's: files as "
        "listed, each file's scene groups reverse-sorted)"
    )
    folder = workdir / "eval_first4"
    assert json.loads((folder / "metrics.json").read_text()) == report
    assert f"\n{stamp}\n" in (folder / "table.md").read_text()
    assert printed[-1] == (folder / "table.md").read_text()

    # Without the rescore command (experiments.evaluate), the same is refused.
    _refused(
        tmp_path / "refused",
        "demon/sun3d/1.0.0 is scored as DeMoN scores it, .* not at hand: ",
        builder=_demon_builder(tiny_scenes),
        method="oracle_pair_median",
        dataset="demon/sun3d",
        open_file_truth=open_file_truth,
    )


def test_the_records_protocol_is_in_the_report_as_written(tiny_scenes, tmp_path):
    workdir = tmp_path / "run"
    report, printed = _oracle(
        workdir, _demon_builder(tiny_scenes), _no_truth, truth_resolution="record"
    )
    assert report["records_protocol"] == DEMON_PROTOCOL
    assert report["protocol"].endswith(
        "order=demon (DeMoN's reader's: files as listed, each file's scene groups reverse-sorted)"
    )
    assert "not DeMoN's protocol" not in report["protocol"]
    assert [text for text in printed if "not by DeMoN's protocol" in text] == []
    folder = workdir / "eval_first4"
    assert json.loads((folder / "metrics.json").read_text()) == report
    # The evaluation folder holds this one evaluation: asked again, it is rewritten with
    # the same stamp, not stamped twice.
    again, _ = _oracle(workdir, _demon_builder(tiny_scenes), _no_truth, truth_resolution="record")
    assert again["protocol"] == report["protocol"]
    assert (folder / "table.md").read_text().count("records built with") == 1


@pytest.mark.skipif(not Path("/proc/self").is_dir(), reason="needs /proc")
def test_a_workdir_that_cannot_be_written_is_refused_before_anything_is_evaluated(
    tiny_scenes, monkeypatch
):
    from gld.evaluation import trained_run

    def evaluated(*args, **kwargs):
        raise AssertionError("evaluated")

    monkeypatch.setattr(trained_run, "evaluate_predictor", evaluated)
    with pytest.raises(ArgumentError) as refused:
        evaluation_run.evaluate_split(
            "/proc/self/run",
            prepare_dataset=lambda name: tiny_scenes,
            open_file_truth=_no_truth,
            dataset="gld_scenes/tiny",
            method="triangulation_gt_pose",
            flow_source="gt",
            print_fn=lambda line: None,
        )
    assert str(refused.value).startswith(
        "the evaluation would be written to /proc/self/run/eval_flow-gt: cannot write in "
        "/proc/self ("
    )


def test_the_final_evaluation_found_is_the_default_protocols_of_that_step(tmp_path):
    def report(folder: str, step: int) -> None:
        (tmp_path / folder).mkdir(exist_ok=True)
        (tmp_path / folder / "metrics.json").write_text(json.dumps({"split": "test", "step": step}))

    report("eval", 6)
    assert evaluation_run.final_evaluation_of(tmp_path, "gld_scenes/tiny", 6) == tmp_path / "eval"
    assert evaluation_run.final_evaluation_of(tmp_path, "gld_scenes/tiny", 8) is None
    # A DeMoN run scored at the records' resolution for want of its files is not DeMoN's
    # protocol: a relaunch with the files evaluates again.
    assert evaluation_run.final_evaluation_of(tmp_path, "demon/sun3d", 6) is None
    report("eval_truth-file", 6)
    assert evaluation_run.final_evaluation_of(tmp_path, "demon/sun3d", 6) == (
        tmp_path / "eval_truth-file"
    )
