"""A recording's prediction folder holds one run (gld/inference/prediction_folder.py): an
earlier run is refused, or with `overwrite` replaced file by file (the predictor's files
only); a run that fails part way leaves the folder as it was. A stand-in predictor keeps
these tests free of a model."""

import json

import cv2
import numpy as np
import pytest

from gld.inference import frames as frames_lib
from gld.inference import prediction_folder, recordings

HEIGHT, WIDTH = 6, 8


class _ConstantPredictor:
    """Depth 2.0 everywhere, scale 1: what `predict_recording` needs of a predictor."""

    height, width, aspect = HEIGHT, WIDTH, "resize"

    def predict(self, images1, images2, **options):
        count = len(images1)
        return {"depth": np.full((count, HEIGHT, WIDTH), 2.0, np.float32), "scale": np.ones(count)}


def _frames(folder, count=4, unreadable=()):
    """`count` frames f0, f1, ...; those in `unreadable` are not images."""
    folder.mkdir()
    paths = [folder / f"f{index}.png" for index in range(count)]
    for index, path in enumerate(paths):
        if index in unreadable:
            path.write_bytes(b"not an image")
        else:
            cv2.imwrite(str(path), np.full((HEIGHT, WIDTH, 3), 40 * index, np.uint8))
    return frames_lib.ImageFolderFrames(paths)


def _predict(frames, out, *, plan=None, **options):
    plan = plan or recordings.plan_recording(recordings.frame_pairs(len(frames)))
    options = {"depth_format": "npy", "batch_size": 2, **options}
    return recordings.predict_recording(_ConstantPredictor(), frames, plan, out, **options)


def _files(folder):
    """Every file under `folder` (hidden ones too) -> its bytes."""
    return {path: path.read_bytes() for path in sorted(folder.rglob("*")) if path.is_file()}


def test_an_earlier_run_is_refused_and_with_overwrite_only_its_files_are_replaced(tmp_path):
    frames = _frames(tmp_path / "frames")
    out = tmp_path / "out"
    _predict(frames, out, previews=True)  # baseline units, .npy, 3 pairs, previews
    (out / "notes.txt").write_text("mine\n")
    (out / "depth" / "README").write_text("mine\n")
    (out / "depth" / "mine.npy").write_bytes(b"mine")  # not named as a pair
    before = _files(out)

    metric = recordings.plan_recording([(0, 1), (2, 3)], positions=np.eye(4, 3))
    with pytest.raises(FileExistsError) as refused:
        _predict(frames, out, plan=metric, depth_format="png")
    assert str(refused.value) == (
        f"{out} holds an earlier prediction (summary.json, pairs.csv, 3 in depth/, 3 in "
        "preview/); pass --overwrite (overwrite=True) to replace its files (and only those), "
        "or choose another output folder"
    )
    assert _files(out) == before

    summary = _predict(frames, out, plan=metric, depth_format="png", overwrite=True)
    assert sorted(path.name for path in out.iterdir()) == [
        "depth",
        "notes.txt",
        "pairs.csv",
        "summary.json",
    ]  # no preview/ left, and no staging folder
    assert sorted(path.name for path in (out / "depth").iterdir()) == [
        "README",
        "f0__f1.png",
        "f2__f3.png",
        "mine.npy",
    ]
    for name in ("notes.txt", "depth/README", "depth/mine.npy"):
        assert (out / name).read_bytes() == before[out / name]
    assert json.loads((out / "summary.json").read_text()) == summary
    assert summary["units"] == "metres" and summary["pairs_written"] == 2
    rows = (out / "pairs.csv").read_text().splitlines()
    assert [row.split(",")[0] for row in rows] == ["pair", "f0__f1", "f2__f3"]


def test_a_run_that_fails_part_way_leaves_the_folder_as_it_was(tmp_path):
    frames = _frames(tmp_path / "frames")
    broken = _frames(tmp_path / "broken", count=6, unreadable={4})
    out = tmp_path / "out"
    # (3, 4) is in the second batch: the first has been predicted when f4 fails.
    with pytest.raises(ValueError, match=r"cannot read image .*f4\.png"):
        _predict(broken, out)
    assert not out.exists()

    _predict(frames, out)
    before = _files(out)
    with pytest.raises(ValueError, match=r"cannot read image .*f4\.png"):
        _predict(broken, out, previews=True, overwrite=True)
    assert _files(out) == before
    assert sorted(path.name for path in out.iterdir()) == ["depth", "pairs.csv", "summary.json"]


def test_an_unfinished_run_counts_as_an_earlier_run(tmp_path):
    out = tmp_path / "out"
    # An older version's run stopped part way: pairs.csv and depth files, no summary.
    (out / "depth").mkdir(parents=True)
    (out / "depth" / "a__b.png").write_bytes(b"png")
    (out / "pairs.csv").write_text(",".join(prediction_folder.PAIRS_HEADER) + "\n")
    # A killed run's staging folder.
    (out / ".predict-x1.partial" / "depth").mkdir(parents=True)
    (out / ".predict-x1.partial" / "depth" / "a__b.npy").write_bytes(b"npy")
    with pytest.raises(FileExistsError) as refused:
        prediction_folder.check_output_dir(out)
    message = str(refused.value)
    assert "pairs.csv, 1 in depth/" in message
    assert ".predict-x1.partial, the staging folder of a run that was stopped" in message

    _predict(_frames(tmp_path / "frames"), out, overwrite=True)
    assert sorted(path.name for path in out.iterdir()) == ["depth", "pairs.csv", "summary.json"]
    assert sorted(path.name for path in (out / "depth").iterdir()) == [
        "f0__f1.npy",
        "f1__f2.npy",
        "f2__f3.npy",
    ]


def test_a_file_the_predictor_did_not_write_is_never_replaced(tmp_path):
    frames = _frames(tmp_path / "frames")
    for name, content in [("pairs.csv", "f0 f2\n"), ("summary.json", "{}"), ("depth", "x")]:
        out = tmp_path / name.replace(".", "_")
        out.mkdir()
        (out / name).write_text(content)
        for overwrite in (False, True):
            with pytest.raises(
                ValueError, match=f"{out / name}: not the predictor's, where the run would"
            ):
                _predict(frames, out, overwrite=overwrite)
            assert [path.name for path in out.iterdir()] == [name]
            assert (out / name).read_text() == content


def test_a_folder_of_other_files_takes_a_run_beside_them(tmp_path):
    frames = _frames(tmp_path / "frames")
    out = tmp_path / "out"
    out.mkdir()
    (out / "range.csv").write_text("frame,u,v,depth\n")
    assert prediction_folder.check_output_dir(out) == []
    _predict(frames, out)
    assert sorted(path.name for path in out.iterdir()) == [
        "depth",
        "pairs.csv",
        "range.csv",
        "summary.json",
    ]


class _GrowingPredictor(_ConstantPredictor):
    """Pair k's depth is k + 1 everywhere (calls count the pairs)."""

    def __init__(self):
        self.done = 0

    def predict(self, images1, images2, **options):
        count = len(images1)
        depth = np.stack([np.full((HEIGHT, WIDTH), self.done + k + 1.0) for k in range(count)])
        self.done += count
        return {"depth": depth.astype(np.float32), "scale": np.ones(count)}


@pytest.mark.parametrize("preview_scale", ["pair", "recording"])
def test_previews_share_one_scale_when_asked(tmp_path, preview_scale):
    frames = _frames(tmp_path / "frames")
    plan = recordings.plan_recording(recordings.frame_pairs(len(frames)))
    out = tmp_path / "out"
    options = dict(depth_format="npy", batch_size=1, previews=True, preview_scale=preview_scale)
    summary = recordings.predict_recording(_GrowingPredictor(), frames, plan, out, **options)
    assert summary["preview_scale"] == preview_scale
    maps = sorted((out / "preview").iterdir())
    colours = [cv2.imread(str(path))[:, WIDTH : 2 * WIDTH] for path in maps]
    if preview_scale == "pair":  # each map at the top of its own scale: all alike
        assert all(np.array_equal(colour, colours[0]) for colour in colours)
    else:  # depths 1, 2, 3 on one scale (the median top, 1/2): 1 and 2 at its top, 3 darker
        brightness = [float(colour.mean()) for colour in colours]
        assert brightness[0] == brightness[1] > brightness[2]
        np.testing.assert_array_equal(
            colours[1], cv2.cvtColor(depth_io_colours(2.0, top=0.5), cv2.COLOR_RGB2BGR)
        )


def depth_io_colours(depth: float, top: float) -> np.ndarray:
    from gld.inference import depth_io

    return depth_io.colourise_inverse_depth(np.full((HEIGHT, WIDTH), depth), top)
