"""Depth maps other systems stored (gld/evaluation/stored_predictions.py): names, formats,
checks."""

import warnings

import cv2
import numpy as np
import pytest

from gld.evaluation import stored_predictions
from gld.evaluation.stored_predictions import StoredPredictions


def test_a_file_is_named_by_its_id_with_slashes_replaced():
    assert stored_predictions.file_stem("sun3d_test.h5/0003/0-1") == "sun3d_test.h5__0003__0-1"
    assert stored_predictions.file_stem("gld_scenes/tiny/test/00015") == (
        "gld_scenes__tiny__test__00015"
    )


def test_npy_and_16_bit_png_files_load_as_depth(tmp_path):
    depth = np.array([[0.5, 2.0], [7.25, 1e-3]])
    np.save(tmp_path / "a.npy", depth)
    loaded = stored_predictions.load_depth(tmp_path / "a.npy")
    assert loaded.dtype == np.float32
    np.testing.assert_array_equal(loaded, depth.astype(np.float32))

    millimetres = np.array([[0, 1500], [65535, 1]], np.uint16)
    cv2.imwrite(str(tmp_path / "b.png"), millimetres)
    np.testing.assert_allclose(
        stored_predictions.load_depth(tmp_path / "b.png"), [[0, 1.5], [65.535, 0.001]], rtol=1e-6
    )
    np.testing.assert_allclose(
        stored_predictions.load_depth(tmp_path / "b.png", png_depth_scale=0.01),
        [[0, 15.0], [655.35, 0.01]],
        rtol=1e-6,
    )


def _write_folder(folder, shapes_and_values):
    folder.mkdir()
    for stem, value in shapes_and_values.items():
        if stem.endswith(".png"):
            cv2.imwrite(str(folder / stem), value)
        else:
            np.save(folder / stem, value)


def test_check_names_every_missing_and_bad_file(tmp_path):
    good = np.full((6, 8), 2.0, np.float32)
    with_nan = good.copy()
    with_nan[2, 3] = np.nan
    folder = tmp_path / "predictions"
    _write_folder(
        folder,
        {
            "run__0.npy": good,
            "run__2.npy": with_nan,
            "run__3.png": np.full((6, 8), 9, np.uint8),
            "run__4.npy": np.zeros((6, 8, 2), np.float32),
            "run__5.npy": good,
            "run__5.png": good.astype(np.uint16),
            "run__6.npy": np.ones((6, 6), np.float32),
            "run__7.npy": np.ones((6, 8), np.int32),
        },
    )
    predictions = StoredPredictions(folder)
    ids = [(f"run/{index}", 1.0) for index in range(8)]
    with pytest.raises(FileNotFoundError) as raised:
        predictions.check(ids, height=48, width=64)
    message = str(raised.value)
    assert f"predictions in {folder} cannot be scored" in message
    assert "1 example(s) without a <name>.npy or <name>.png: run__1\n" in message
    assert '"/" replaced by "__"' in message
    assert f"{folder / 'run__2.npy'}: 1 NaN or inf value(s)" in message
    assert f"{folder / 'run__3.png'}: uint8 with 1 channel(s), expected a 16-bit" in message
    assert f"{folder / 'run__4.npy'}: shape (6, 8, 2), expected a 2-D" in message
    assert "both run__5.npy and run__5.png exist" in message
    assert f"{folder / 'run__6.npy'}: shape (6, 6), expected the aspect ratio" in message
    assert f"{folder / 'run__7.npy'}: dtype int32, expected floating-point" in message
    # One line per bad file (six), none for the good one.
    problems = [line for line in message.splitlines() if line.strip().startswith(str(folder))]
    problems += [line for line in message.splitlines() if "both run__5" in line]
    assert len(problems) == 6 and not any("run__0" in line for line in problems)

    # Every file present: the bad ones raise ValueError; the good one passes alone.
    with pytest.raises(ValueError, match="run__2.npy: 1 NaN") as raised:
        predictions.check([ids[0], ids[2]], height=48, width=64)
    assert not isinstance(raised.value, FileNotFoundError)
    with pytest.warns(UserWarning, match=r"7 file\(s\) named by no example scored here"):
        predictions.check([ids[0]], height=48, width=64)


def test_a_missing_folder_and_unchecked_ids_are_refused(tmp_path):
    with pytest.raises(FileNotFoundError, match="does_not_exist does not exist"):
        StoredPredictions(tmp_path / "does_not_exist")
    with pytest.raises(ValueError, match="depth_scale"):
        StoredPredictions(tmp_path, depth_scale="metres")
    predictions = StoredPredictions(tmp_path)
    with pytest.raises(ValueError, match="not checked"):
        predictions.predict({"id": np.array(["a/0"]), "depth": np.zeros((1, 6, 8))})


def test_predictions_are_resized_by_nearest_neighbour_and_brought_to_unit_baseline(tmp_path):
    rng = np.random.default_rng(0)
    depth = rng.uniform(1.0, 9.0, (6, 8)).astype(np.float32)
    folder = tmp_path / "predictions"
    # Twice the evaluation resolution, each value repeated 2x2: nearest neighbour from
    # the centres of the output pixels finds the original values again.
    _write_folder(folder, {"a__0.npy": np.repeat(np.repeat(depth, 2, 0), 2, 1), "a__1.npy": depth})
    batch = {"id": np.array(["a/0", "a/1", "a/0"]), "depth": np.zeros((3, 6, 8), np.float32)}

    normalised = StoredPredictions(folder)
    normalised.check([("a/0", 4.0), ("a/1", 0.5)], height=6, width=8)
    np.testing.assert_array_equal(normalised.predict(batch)["depth"], [depth, depth, depth])
    note = normalised.protocol_note()
    assert note == (
        f"stored predictions from {folder} (normalised depth (||t|| = 1)): 1 at 8x6, "
        "1 at 16x12 resized to 8x6 by centre-aligned nearest neighbour"
    )

    raw = StoredPredictions(folder, depth_scale="raw")
    raw.check([("a/0", 4.0), ("a/1", 0.5)], height=6, width=8)
    predicted = raw.predict(batch)["depth"]
    np.testing.assert_allclose(predicted, [depth / 4.0, depth / 0.5, depth / 4.0], rtol=1e-7)
    assert "raw depth divided by each pair's ||t||" in raw.protocol_note()
    assert raw.summary()["prediction_resolutions"] == {"8x6": 1, "16x12": 1}


def test_with_truth_shapes_each_map_goes_straight_to_its_examples_resolution(tmp_path):
    depth = np.random.default_rng(1).uniform(1.0, 9.0, (6, 8)).astype(np.float32)
    doubled = np.repeat(np.repeat(depth, 2, 0), 2, 1)
    folder = tmp_path / "predictions"
    _write_folder(folder, {"a__0.npy": doubled, "a__1.npy": depth})
    predictions = StoredPredictions(folder)
    # The records are 8x6; the truth of a/0 is 16x12 (its file's), of a/1 32x24.
    predictions.check(
        [("a/0", 1.0), ("a/1", 1.0)], height=6, width=8, shapes={"a/0": (12, 16), "a/1": (24, 32)}
    )
    maps = predictions.predict({"id": np.array(["a/0", "a/1"]), "depth": np.zeros((2, 6, 8))})
    np.testing.assert_array_equal(maps["depth"][0], doubled)  # not through 8x6
    np.testing.assert_array_equal(maps["depth"][1], np.repeat(np.repeat(depth, 4, 0), 4, 1))
    assert predictions.protocol_note().endswith(
        ": 1 at 8x6 resized to 32x24 by centre-aligned nearest neighbour, 1 at 16x12"
    )
    with pytest.raises(
        ValueError, match=r"expected the aspect ratio of the evaluation resolution \[12, 12\]"
    ):
        predictions.check([("a/0", 1.0)], height=6, width=8, shapes={"a/0": (12, 12)})


def test_a_file_of_no_scored_example_is_named_in_a_warning_and_in_the_record(tmp_path):
    depth = np.full((6, 8), 2.0, np.float32)
    folder = tmp_path / "predictions"
    # a__9.npy is no example's; a__1.jpg is in a format that is not read.
    _write_folder(folder, {"a__0.npy": depth, "a__1.npy": depth, "a__9.npy": depth})
    (folder / "a__1.jpg").write_bytes(b"jpeg")
    predictions = StoredPredictions(folder)
    with pytest.warns(UserWarning) as caught:
        predictions.check([("a/0", 1.0), ("a/1", 1.0)], height=6, width=8)
    unscored = "2 file(s) named by no example scored here, left out: a__1.jpg, a__9.npy"
    assert [str(warning.message) for warning in caught] == [
        f'predictions in {folder}: {unscored} (a file is named by its example id with "/" '
        'replaced by "__")'
    ]
    assert predictions.protocol_note() == (
        f"stored predictions from {folder} (normalised depth (||t|| = 1)): 2 at 8x6; {unscored}"
    )
    assert predictions.summary()["predictions_unscored_files"] == ["a__1.jpg", "a__9.npy"]

    # Every file an example's: no warning, nothing recorded.
    (folder / "a__1.jpg").unlink()
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        predictions.check([("a/0", 1.0), ("a/1", 1.0), ("a/9", 1.0)], height=6, width=8)
    assert predictions.protocol_note().endswith(": 3 at 8x6")
    assert predictions.summary()["predictions_unscored_files"] == []
