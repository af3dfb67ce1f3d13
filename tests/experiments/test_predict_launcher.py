"""`python -m experiments.predict` end to end in a subprocess: a folder of frames with
range readings and intrinsics -> metric depth PNGs, previews, point clouds; bad flags
are refused by name before anything is written; an output folder holds one run (an
earlier one refused in one line, or replaced with --overwrite; a run failing part way
leaves nothing); --measure_scale on the tiny benchmark."""

import csv
import json
import re

import cv2
import numpy as np
import pytest
from conftest import launch, tiny_train_config

from data.demon import recordings
from gld.evaluation import stored_predictions
from gld.inference import depth_io, recording_run
from gld.runs import workdir as workdir_lib

HEIGHT, WIDTH = 72, 96  # the tiny model's 4:3 at 1.5x its 64x48
FX, FY, CX, CY = 80.0, 82.0, 47.0, 35.5


def _launch(*args):
    return launch("experiments.predict", *args, timeout=600)


def _recording(folder):
    """Four frames of a texture moving right, and range readings on frames 0 and 2."""
    rng = np.random.default_rng(0)
    texture = cv2.GaussianBlur(rng.integers(0, 256, (HEIGHT, WIDTH + 12, 3), np.uint8), (5, 5), 0)
    frames = folder / "frames"
    frames.mkdir()
    for index in range(4):
        frame = texture[:, 3 * index : 3 * index + WIDTH]
        cv2.imwrite(str(frames / f"frame_{index}.png"), frame)
    ranges = folder / "range.csv"
    ranges.write_text("frame,u,v,depth\nframe_0,40,30,2.0\n2,10.5,60,3.5\nframe_3,5,5,1.0\n")
    return frames, ranges


def test_predict_writes_metric_depth_previews_and_point_clouds(trained_workdir, tmp_path):
    frames, ranges = _recording(tmp_path)
    out = tmp_path / "out"
    result = _launch(
        f"--workdir={trained_workdir}",
        f"--images={frames}",
        f"--ranges={ranges}",
        f"--intrinsics={FX},{FY},{CX},{CY}",
        f"--output_dir={out}",
        "--batch_size=2",
        "--previews",
        "--ply",
    )
    assert result.returncode == 0, result.stderr[-3000:]
    # Pairs (0, 1), (1, 2), (2, 3); frame 1 has no reading, so its pair is skipped.
    names = ["frame_0__frame_1", "frame_2__frame_3"]
    assert "2 pair(s) written" in result.stdout and "1 no range reading" in result.stdout
    assert sorted(p.stem for p in (out / "depth").iterdir()) == names
    assert sorted(p.stem for p in (out / "preview").iterdir()) == names
    summary = json.loads((out / "summary.json").read_text())
    assert summary["units"] == "metres" and summary["depth_format"] == "png"
    assert summary["pairs_skipped"] == {"no range reading on the first frame": 1}
    rows = list(csv.DictReader((out / "pairs.csv").open()))
    assert [row["pair"] for row in rows] == names and rows[0]["scale_source"] == "ranges"

    preview = cv2.imread(str(out / "preview" / f"{names[0]}.png"))
    # The image, the map, and its colour bar in metres (as wide as its labels).
    assert preview.shape[0] == HEIGHT and preview.shape[1] > 2 * WIDTH + 12
    np.testing.assert_array_equal(preview[:, -4:], 255)
    for name, (u, v, distance) in zip(names, [(40, 30, 2.0), (10.5, 60, 3.5)], strict=True):
        depth = stored_predictions.load_depth(out / "depth" / f"{name}.png")  # millimetres
        assert depth.shape == (HEIGHT, WIDTH) and np.all(depth > 0)
        # The metric map passes through the reading (bilinear, to the PNG's millimetre).
        column = int(u)
        weight = u - column
        at_reading = (1 - weight) * depth[int(v), column] + weight * depth[int(v), column + 1]
        assert abs(at_reading - distance) < 2e-3
        cloud = depth_io.read_ply(out / "ply" / f"{name}.ply")
        points = cloud["points"]
        assert points.shape == (HEIGHT * WIDTH, 3) and cloud["colours"].shape == points.shape
        # One point per pixel in row-major order, at the metric depth of the PNG.
        np.testing.assert_allclose(points[:, 2], depth.reshape(-1), atol=6e-4)
        row, col = 50, 20
        np.testing.assert_allclose(
            points[row * WIDTH + col],
            np.array([(col - CX) / FX, (row - CY) / FY, 1.0]) * depth[row, col],
            atol=2e-3,
        )


@pytest.mark.slow
def test_bad_flags_are_named_before_anything_is_written(trained_workdir, tmp_path):
    frames, _ = _recording(tmp_path)
    empty = tmp_path / "empty"
    empty.mkdir()
    bad_csv = tmp_path / "bad.csv"
    bad_csv.write_text("frame_0,1,2\n")
    out = tmp_path / "out"
    cases = [
        ([f"--images={tmp_path / 'missing'}"], "--images: image folder .*missing does not exist"),
        ([f"--images={empty}"], "--images: no images .* in .*empty"),
        ([f"--images={frames}", "--intrinsics=1,2,3", "--ply"], "--intrinsics: .*expected 4"),
        ([f"--images={frames}", f"--ranges={bad_csv}"], "--ranges: .*bad.csv:1: expected frame"),
    ]
    for args, message in cases:
        result = _launch(f"--workdir={trained_workdir}", f"--output_dir={out}", *args)
        assert result.returncode != 0, args
        assert re.search(message, result.stderr), (message, result.stderr[-2000:])
        assert not out.exists(), args


@pytest.mark.slow  # loads a workdir and a dataset in a subprocess: ~20 s of CPU
def test_measure_scale_on_the_tiny_benchmark(trained_workdir, tiny_scenes_dir, tmp_path):
    result = _launch(
        f"--workdir={trained_workdir}",
        "--measure_scale",
        f"--data_dir={tiny_scenes_dir}",
        "--max_examples=4",
        "--batch_size=4",
        f"--output_dir={tmp_path}",
    )
    assert result.returncode == 0, result.stderr[-3000:]
    stored = json.loads((tmp_path / "scale_recovery.json").read_text())
    assert stored["num_examples"] == 4 and stored["dataset"].startswith("gld_scenes/tiny")
    methods = stored["methods"]
    assert set(methods) == {
        "true_baseline",
        "one_reading",
        "train_mean_baseline",
        "oracle_best_scale",
    }
    for name, entry in methods.items():
        assert np.isfinite(entry["abs_rel"]) and len(stored["per_example"][name]) == 4
    # The per-pair best scale is the lower bound of every single-scale method, pair by pair.
    best = np.asarray(stored["per_example"]["oracle_best_scale"])
    for name in ("true_baseline", "one_reading", "train_mean_baseline"):
        assert np.all(best <= np.asarray(stored["per_example"][name]) + 1e-6)
    assert "training-set mean baseline" in result.stdout


def _files(folder):
    """Every file under `folder` (hidden ones too) -> its bytes."""
    return {path: path.read_bytes() for path in sorted(folder.rglob("*")) if path.is_file()}


def _error_line(stderr):
    """The launcher's error, its last line: no traceback and no dump of the flags' help
    (a progress bar may come before it)."""
    assert "Traceback" not in stderr and "flags:" not in stderr, stderr[-3000:]
    return stderr.strip().splitlines()[-1]


def test_an_output_folder_holds_one_run(trained_workdir, tmp_path):
    frames, ranges = _recording(tmp_path)
    out = tmp_path / "out"
    # The earlier run, metric depth in 16-bit PNGs with previews, made here by the
    # library's run of the launcher (a process fewer).
    recording_run.predict_recording_run(
        trained_workdir,
        out,
        files=recordings,
        images=str(frames),
        ranges=str(ranges),
        depth_format="png",
        previews=True,
        batch_size=2,
    )
    assert sorted(path.name for path in (out / "preview").iterdir()) == [
        "frame_0__frame_1.png",
        "frame_2__frame_3.png",
    ]
    options = [f"--workdir={trained_workdir}", f"--images={frames}", f"--output_dir={out}"]
    # Files of the user's own beside the run's, in the folder and among the depth files.
    (out / "notes.txt").write_text("mine\n")
    (out / "depth" / "README").write_text("mine\n")
    before = _files(out)

    # Another run (baseline units, .npy) is refused before anything is written.
    refused = _launch(*options, "--batch_size=2")
    assert refused.returncode != 0
    assert len(refused.stderr.strip().splitlines()) == 1, refused.stderr[-3000:]
    message = _error_line(refused.stderr)
    assert re.fullmatch(r"--output_dir: .*out holds an earlier prediction .*--overwrite.*", message)
    assert _files(out) == before

    # With --overwrite it replaces the earlier run's files, and only those.
    replaced = _launch(*options, "--batch_size=2", "--overwrite")
    assert replaced.returncode == 0, replaced.stderr[-3000:]
    names = ["frame_0__frame_1", "frame_1__frame_2", "frame_2__frame_3"]
    assert sorted(path.name for path in out.iterdir()) == [
        "depth",
        "notes.txt",
        "pairs.csv",
        "summary.json",
    ]
    assert sorted(path.name for path in (out / "depth").iterdir()) == [
        "README",
        *[f"{name}.npy" for name in names],
    ]
    assert (out / "notes.txt").read_text() == (out / "depth" / "README").read_text() == "mine\n"
    summary = json.loads((out / "summary.json").read_text())
    assert summary["units"] == "baseline" and summary["depth_format"] == "npy"
    assert summary["pairs_written"] == 3 and summary["previews"] is False
    rows = list(csv.DictReader((out / "pairs.csv").open()))
    assert [row["pair"] for row in rows] == names
    assert {row["units"] for row in rows} == {"baseline"}


def test_a_run_that_fails_part_way_leaves_the_folder_as_it_was(trained_workdir, tmp_path):
    frames, _ = _recording(tmp_path)
    # A fifth frame that is no image: the pair (3, 4) fails after the first batch is written.
    (frames / "frame_4.png").write_bytes(b"not an image")
    out = tmp_path / "out"
    options = [f"--workdir={trained_workdir}", f"--images={frames}", "--batch_size=2"]
    failed = _launch(*options, f"--output_dir={out}")
    assert failed.returncode != 0
    message = _error_line(failed.stderr)
    assert re.fullmatch(r"--images: .*cannot read image .*frame_4\.png.*", message), message
    assert not out.exists()


def test_a_match_frames_refusal_is_one_line(tmp_path):
    """Frames named frame_<i> cannot be matched by time: one line naming the flag, exit
    status 2, before the model is loaded (a workdir with only its config)."""
    frames, _ = _recording(tmp_path)
    poses = tmp_path / "poses.txt"
    poses.write_text("".join(f"{1305031102.1 + t} {t} 0 0 0 0 0 1\n" for t in range(4)))
    workdir = tmp_path / "run"
    workdir_lib.write_run_config(workdir, tiny_train_config())
    out = tmp_path / "out"
    result = _launch(
        f"--workdir={workdir}",
        f"--images={frames}",
        f"--poses={poses}",
        "--match_frames=time",
        f"--output_dir={out}",
    )
    assert result.returncode == 2, result.stderr[-3000:]
    assert len(result.stderr.strip().splitlines()) == 1, result.stderr[-3000:]
    message = _error_line(result.stderr)
    assert re.fullmatch(
        r"--match_frames=time: .*frame_0\.png is not named by a time stamp .*"
        r"--match_frames=order matches by order",
        message,
    ), message
    assert not out.exists()
