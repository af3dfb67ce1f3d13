"""Ground truth at the files' resolution (data/demon/file_truth.py), scored as DeMoN's
evaluation scores it: a tiny demon/sun3d test split built from 640x480 files written
by `demon_files`, evaluated against those files and checked against numpy by hand; and
DeMoN's protocol as the default of a demon/* evaluation (gld/evaluation/evaluation_run.py,
experiments/evaluate.py)."""

from __future__ import annotations

import csv
import json
import os
import shutil
import subprocess
import sys
from types import SimpleNamespace

import demon_files
import h5py
import numpy as np
import pytest
from conftest import REPO_ROOT

import data
from data.demon import file_truth, reader
from gld import input_pipeline
from gld.evaluation import evaluation_run, stored_predictions, trained_run

FILE_HEIGHT, FILE_WIDTH = 480, 640  # SUN3D's and RGB-D's files
HEIGHT, WIDTH = 192, 256  # the records'
SCENES = ("kitchen", "office", "stairs")


def _written_views(rng):
    """scene -> its two views; view 0's depth has invalid pixels (0 and NaN)."""
    scenes = {}
    for scene in SCENES:
        views = demon_files.moving_views(rng, 2, FILE_HEIGHT, FILE_WIDTH)
        views[0]["depth"][100:110, 200:260] = 0.0
        views[0]["depth"][300, 300:310] = np.nan
        scenes[scene] = views
    return scenes


@pytest.fixture(scope="module")
def demon_sun3d(tmp_path_factory):
    """(manual_dir, built builder, {id: (file depth as read [480, 640], ||t|| by hand)});
    the data_dir is the builder's `gld_data_dir`."""
    root = tmp_path_factory.mktemp("demon_file_truth")
    manual_dir = root / "manual"
    manual_dir.mkdir()
    scenes = _written_views(np.random.default_rng(3))
    with h5py.File(manual_dir / "sun3d_test.h5", "w") as h5_file:
        for scene, views in scenes.items():
            demon_files.write_scene(h5_file, scene, views)
    builder = data.prepare("demon/sun3d", root / "datasets", manual_dir, verify_checksums=False)
    builder.gld_data_dir = root / "datasets"
    expected = {}
    for scene, (view1, view2) in scenes.items():
        depth = view1["depth"].astype(np.float16).astype(np.float32)  # stored as float16
        relative_rotation = view2["rotation"] @ view1["rotation"].T
        translation = view2["translation"] - relative_rotation @ view1["translation"]
        baseline = float(np.linalg.norm(translation.astype(np.float32)))
        expected[f"sun3d_test.h5/{scene}/0-1"] = (depth, baseline)
    return manual_dir, builder, expected


def _demon_upsampled(prediction, height, width):
    """DeMoN's evaluation resize (scikit-image, order 0) by hand: each output pixel
    takes the input pixel under its centre."""
    rows = np.floor((np.arange(height) + 0.5) * prediction.shape[0] / height).astype(int)
    cols = np.floor((np.arange(width) + 0.5) * prediction.shape[1] / width).astype(int)
    return prediction[rows][:, cols]


def _abs_inv(prediction, truth):
    """DeMoN's Abs-Inv over the valid truth pixels with a positive prediction, and the
    valid truth pixels excluded for their prediction."""
    valid = np.isfinite(truth) & (truth > 0)
    scored = valid & (prediction > 0)
    error = np.abs(1.0 / truth[scored] - 1.0 / prediction[scored].astype(np.float64)).mean()
    return float(error), int((valid & ~scored).sum())


def _per_example(workdir, method):
    with (workdir / "eval_truth-file" / f"per_example_{method}.csv").open() as stream:
        return {row["id"]: row for row in csv.DictReader(stream)}


def test_example_ids_name_file_group_and_pair():
    example_id = reader.example_id("sun3d_test.h5", "0003", (0, 1))
    assert file_truth.parse_example_id(example_id) == ("sun3d_test.h5", "0003", (0, 1))
    for bad in ("scene/0-1", "a.h5/s/0-x", "a.h5/s/t/0-1", "/s/0-1"):
        with pytest.raises(ValueError, match="is not '<file>/<group>/<i>-<j>'"):
            file_truth.parse_example_id(bad)


def test_the_truth_is_view_1_of_the_file_scaled_as_the_record(demon_sun3d):
    manual_dir, builder, expected = demon_sun3d
    source = builder.as_data_source("test")
    with file_truth.FileTruth(manual_dir) as truth:
        truth.check(stored_predictions.record_ids_and_baselines(source))
        assert truth.shapes() == {example_id: (480, 640) for example_id in expected}
        ids = sorted(expected)
        for example_id, (depth, valid) in zip(ids, truth.maps(ids), strict=True):
            file_depth, baseline = expected[example_id]
            expected_valid = np.isfinite(file_depth) & (file_depth > 0)
            np.testing.assert_array_equal(valid, expected_valid)
            assert valid.sum() == 480 * 640 - 600 - 10
            np.testing.assert_allclose(
                depth, np.where(expected_valid, file_depth / baseline, 0.0), rtol=1e-6
            )


def test_the_examples_checked_last_are_not_read_again(demon_sun3d, monkeypatch):
    manual_dir, builder, expected = demon_sun3d
    examples = list(stored_predictions.record_ids_and_baselines(builder.as_data_source("test")))
    with file_truth.FileTruth(manual_dir) as truth:
        read = []
        original = truth._view
        monkeypatch.setattr(truth, "_view", lambda *args: read.append(args) or original(*args))
        truth.check(examples)
        assert len(read) == 2 * len(expected)  # both views of every example
        truth.check(iter(examples))  # where it was opened, then by the scorer
        assert len(read) == 2 * len(expected)
        truth.check(examples[:1])  # other examples are read
        assert len(read) == 2 * len(expected) + 2
        assert list(truth.shapes()) == [examples[0][0]]


def test_other_files_than_the_records_were_built_from_are_refused(demon_sun3d, tmp_path):
    _, builder, _ = demon_sun3d
    examples = stored_predictions.record_ids_and_baselines(builder.as_data_source("test"))
    other = tmp_path / "other"
    other.mkdir()
    with h5py.File(other / "sun3d_test.h5", "w") as h5_file:
        views = demon_files.moving_views(np.random.default_rng(0), 2, 48, 64)
        views[1]["translation"] = 2 * views[1]["translation"]  # another baseline
        demon_files.write_scene(h5_file, "kitchen", views)
    with file_truth.FileTruth(other) as truth, pytest.raises(ValueError) as error:
        truth.check(examples)
    message = str(error.value)
    assert "for 3 example(s)" in message and "it must hold the DeMoN files" in message
    assert "sun3d_test.h5/kitchen/0-1: ||t|| is" in message
    assert "sun3d_test.h5/office/0-1: " in message  # no such group in the other file
    with pytest.raises(FileNotFoundError, match="does not exist"):
        file_truth.FileTruth(tmp_path / "nowhere")


def test_scores_at_the_files_resolution_follow_demons_rule(demon_sun3d, tmp_path):
    manual_dir, builder, expected = demon_sun3d
    source = builder.as_data_source("test")
    folder = tmp_path / "predictions"
    folder.mkdir()
    predictions, record_truth = {}, {}
    for batch in input_pipeline.eval_batches(source, batch_size=4):
        for example_id, depth, real in zip(
            batch["id"], batch["depth"], batch["example_mask"], strict=True
        ):
            if not real:
                continue
            # The record's truth, wrong by up to 30% in a pattern, with no prediction in
            # its top two rows.
            y, x = np.mgrid[0:HEIGHT, 0:WIDTH]
            prediction = np.where(depth > 0, depth, 1.0) * (1 + 0.3 * np.sin(x / 7) * np.cos(y / 5))
            prediction[:2] = 0.0
            predictions[example_id] = prediction.astype(np.float32)
            record_truth[example_id] = depth
            np.save(
                folder / f"{stored_predictions.file_stem(example_id)}.npy", predictions[example_id]
            )

    with file_truth.FileTruth(manual_dir) as truth:
        report = trained_run.evaluate_workdir(
            tmp_path / "run",
            source,
            height=HEIGHT,
            width=WIDTH,
            num_figures=1,
            predictions=stored_predictions.StoredPredictions(folder),
            truth=truth,
            print_fn=lambda _: None,
        )
    rows = _per_example(tmp_path / "run", "stored_predictions")
    assert sorted(rows) == sorted(expected)
    for example_id, row in rows.items():
        file_depth, baseline = expected[example_id]
        truth_depth = file_depth.astype(np.float64) / baseline
        upsampled = _demon_upsampled(predictions[example_id], FILE_HEIGHT, FILE_WIDTH)
        at_file, excluded = _abs_inv(upsampled, truth_depth)
        at_record, _ = _abs_inv(predictions[example_id], record_truth[example_id])
        assert float(row["abs_inv"]) == pytest.approx(at_file, rel=1e-5)
        assert float(row["excluded_pixels"]) == excluded == 5 * 640  # file rows 0-4
        # Scoring at the records' resolution would give another number.
        assert abs(at_file / at_record - 1) > 0.01
    assert report["truth_resolution"] == "file"
    assert report["truth_resolutions"] == {"640x480": 3}
    assert report["truth_files"] == str(manual_dir)
    assert report["protocol"].startswith(
        "protocol: ground truth at the source files' resolution (3 at 640x480), read from "
        "the files by example id, each prediction resized to it by centre-aligned nearest "
        "neighbour as DeMoN's evaluation does (records at 256x192 px)"
    )
    assert "3 at 256x192 resized to 640x480" in report["protocol"]
    assert len(list((tmp_path / "run" / "eval_truth-file" / "figures").glob("*.png"))) == 1


def _exact_predictions(expected, folder):
    """The files' own depth, in metres, as another system's stored predictions."""
    folder.mkdir()
    for example_id, (file_depth, _) in expected.items():
        raw = np.where(np.isfinite(file_depth), file_depth, 0.0).astype(np.float32)
        np.save(folder / f"{stored_predictions.file_stem(example_id)}.npy", raw)
    return folder


def test_an_exact_prediction_at_the_files_resolution_scores_zero(demon_sun3d, tmp_path):
    manual_dir, builder, expected = demon_sun3d
    folder = _exact_predictions(expected, tmp_path / "exact")
    with file_truth.FileTruth(manual_dir) as truth:
        report = trained_run.evaluate_workdir(
            tmp_path / "run",
            builder.as_data_source("test"),
            height=HEIGHT,
            width=WIDTH,
            num_figures=0,
            predictions=stored_predictions.StoredPredictions(folder, depth_scale="raw"),
            truth=truth,
            print_fn=lambda _: None,
        )
    stored = report["methods"]["stored_predictions"]
    assert stored["abs_inv"] == {"mean": 0.0, "std": 0.0, "count": 3}
    assert stored["num_pixels"]["mean"] == 480 * 640 - 610
    assert "3 at 640x480 (" not in report["protocol"]  # not resized
    # The oracle takes its constant from the truth it is scored on.
    for example_id, row in _per_example(tmp_path / "run", "oracle_pair_median").items():
        file_depth, baseline = expected[example_id]
        inv_depth = baseline / file_depth[np.isfinite(file_depth) & (file_depth > 0)]
        by_hand = np.abs(inv_depth - np.median(inv_depth)).mean()
        assert float(row["abs_inv"]) == pytest.approx(by_hand, rel=1e-4)


def test_file_truth_of_a_split_is_read_from_the_files_it_was_built_from(demon_sun3d, tmp_path):
    manual_dir, builder, _ = demon_sun3d
    # Without a folder: where the build found its files.
    with file_truth.for_split(builder, "test") as truth:
        assert truth.manual_dir == manual_dir.resolve()
    copy = tmp_path / "copy"
    copy.mkdir()
    shutil.copy(manual_dir / "sun3d_test.h5", copy)
    with file_truth.for_split(builder, "test", copy) as truth:
        assert truth.manual_dir == copy  # the same content elsewhere
    with pytest.raises(FileNotFoundError, match=f"sun3d_test.h5 not in {tmp_path}"):
        file_truth.for_split(builder, "test", tmp_path)
    with h5py.File(copy / "sun3d_test.h5", "a") as h5_file:
        h5_file.create_group("extra")
    with pytest.raises(ValueError, match="are not those the test split was built from"):
        file_truth.for_split(builder, "test", copy)
    moved = SimpleNamespace(
        info=SimpleNamespace(
            full_name="demon/sun3d/2.0.0",
            metadata={"sources": {"test": {"sun3d_test.h5": {"path": str(tmp_path / "gone/x")}}}},
        )
    )
    with pytest.raises(FileNotFoundError, match="gone does not exist"):
        file_truth.for_split(moved, "test")


def _evaluate(builder, workdir, **arguments):
    return evaluation_run.evaluate_split(
        workdir,
        prepare_dataset=lambda name: builder,
        open_file_truth=file_truth.for_split,
        dataset="demon/sun3d",
        method="oracle_pair_median",
        num_figures=0,
        with_sfm_flow=False,
        print_fn=lambda _: None,
        **arguments,
    )


def test_a_demon_dataset_is_evaluated_by_demons_protocol_by_default(demon_sun3d, tmp_path):
    _, builder, _ = demon_sun3d
    report = _evaluate(builder, tmp_path / "run", max_examples=2)
    # At the files' resolution, from the files the build recorded, in DeMoN's order:
    # the first two pairs are DeMoN's first two.
    assert report["truth_resolution"] == "file" and report["truth_resolutions"] == {"640x480": 2}
    folder = tmp_path / "run" / "eval_first2_truth-file"
    with (folder / "per_example_oracle_pair_median.csv").open() as stream:
        ids = [row["id"] for row in csv.DictReader(stream)]
    assert ids == ["sun3d_test.h5/stairs/0-1", "sun3d_test.h5/office/0-1"]
    protocol = {"image_decoder": "demon", "depth_resampling": "demon", "order": "demon"}
    assert report["records_protocol"] == protocol
    stored = json.loads((folder / "metrics.json").read_text())
    assert stored == report
    note = (
        "records built with image_decoder=demon, depth_resampling=demon; evaluated in the "
        "records' stored order, order=demon (DeMoN's reader's: files as listed, each file's "
        "scene groups reverse-sorted)"
    )
    assert report["protocol"].endswith(f"; {note}")
    assert f"\n{report['protocol']}\n" in (folder / "table.md").read_text()
    # The records' resolution, asked for by name, names the same records' protocol.
    record = _evaluate(builder, tmp_path / "run", truth_resolution="record")
    assert record["truth_resolution"] == "record" and record["records_protocol"] == protocol
    assert "ground truth at the records' resolution, 256x192 px" in record["protocol"]
    assert (tmp_path / "run" / "eval" / "metrics.json").exists()


def test_evaluate_scores_demon_datasets_by_demons_protocol_end_to_end(demon_sun3d, tmp_path):
    manual_dir, builder, expected = demon_sun3d
    folder = _exact_predictions(expected, tmp_path / "exact")
    workdir = tmp_path / "run"
    # Neither --manual_dir nor --truth_resolution: the files the build recorded.
    command = [
        sys.executable,
        "-m",
        "experiments.evaluate",
        f"--predictions={folder}",
        "--predictions_scale=raw",
        "--dataset=demon/sun3d",
        f"--data_dir={builder.gld_data_dir}",
        f"--workdir={workdir}",
        "--num_figures=0",
    ]
    env = dict(os.environ, JAX_PLATFORMS="cpu", PYTHONPATH=str(REPO_ROOT))
    result = subprocess.run(
        command, capture_output=True, text=True, env=env, cwd=REPO_ROOT, timeout=300
    )
    assert result.returncode == 0, result.stderr[-3000:]
    report = json.loads((workdir / "eval_truth-file" / "metrics.json").read_text())
    assert report["methods"]["stored_predictions"]["abs_inv"]["mean"] == 0.0
    assert report["truth_resolution"] == "file" and report["truth_resolutions"] == {"640x480": 3}
    assert report["truth_files"] == str(manual_dir.resolve())
    assert "ground truth at the source files' resolution (3 at 640x480)" in result.stdout
    assert "records built with image_decoder=demon, depth_resampling=demon;" in result.stdout
    rows = _per_example(workdir, "stored_predictions")
    assert list(rows) == [f"sun3d_test.h5/{scene}/0-1" for scene in sorted(SCENES, reverse=True)]
