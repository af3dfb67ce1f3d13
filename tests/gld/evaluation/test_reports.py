"""Evaluation reports (gld/evaluation/reports.py): tables carry their references; figures share one
colour scale."""

import csv
import json

import numpy as np
import pytest

from gld.evaluation import reports

ORACLE_ROW = "| oracle_pair_median — per-pair oracle constant (sees the truth) |"
SFM_ROW = "| sfm_flow — classical pipeline on the same flow (no training) |"


def _per_example(abs_inv, mask):
    count = len(abs_inv)
    return {
        "abs_inv": np.asarray(abs_inv, np.float64),
        "abs_rel": np.full(count, 0.5),
        "s_rmse": np.full(count, 0.25),
        "example_mask": np.asarray(mask, bool),
    }, [f"pair/{index}" for index in range(count)]


def test_report_labels_the_oracle_and_gives_each_method_as_a_multiple_of_the_mean(tmp_path):
    # The third row of each method is padding (mask False): it must not count.
    results = {
        "global_local": _per_example([0.02, 0.04, 9.0], [True, True, False]),
        "dataset_mean": _per_example([0.03, 0.05, 9.0], [True, True, False]),
        "oracle_pair_median": _per_example([0.01, 0.01, 9.0], [True, True, False]),
    }
    report = reports.write_report(tmp_path, results, height=48, width=64, info={"split": "x"})

    assert list(report["methods"]) == ["global_local", "dataset_mean", "oracle_pair_median"]
    assert report["methods"]["global_local"]["abs_inv"]["mean"] == pytest.approx(0.03)
    assert report["abs_inv_vs_dataset_mean"] == pytest.approx(
        {"global_local": 0.75, "dataset_mean": 1.0, "oracle_pair_median": 0.25}
    )
    assert report["labels"] == {"oracle_pair_median": "per-pair oracle constant (sees the truth)"}
    assert json.loads((tmp_path / "metrics.json").read_text()) == report

    lines = (tmp_path / "table.md").read_text().splitlines()
    assert lines[0].endswith("| Abs-Inv ÷ dataset_mean |")
    assert lines[2].startswith("| global_local | 0.0300 ± 0.0100 |") and lines[2].endswith(
        "| 0.75× |"
    )
    assert lines[3].startswith("| dataset_mean |") and lines[3].endswith("| 1.00× |")
    assert lines[4].startswith(ORACLE_ROW) and lines[4].endswith("| 0.25× |")
    with (tmp_path / "per_example_oracle_pair_median.csv").open() as stream:
        rows = list(csv.DictReader(stream))
    assert [row["id"] for row in rows] == ["pair/0", "pair/1"]


def test_report_names_the_records_protocol_once_written(tmp_path):
    results = {"dataset_mean": _per_example([0.03, 0.05], [True, True])}
    protocol = {"image_decoder": "opencv", "depth_resampling": "centred", "order": "demon"}
    report = reports.write_report(
        tmp_path,
        results,
        height=48,
        width=64,
        info={"split": "test"},
        protocol_note="depth maps read as stored",
        records_protocol=protocol,
    )
    # The caller's clause, then the records' protocol, at the end of one stamp.
    assert report["protocol"].endswith(
        "no median scaling; depth maps read as stored; records built with "
        "image_decoder=opencv, depth_resampling=centred; evaluated in the records' stored "
        "order, order=demon (DeMoN's reader's: files as listed, each file's scene groups "
        "reverse-sorted)"
    )
    assert report["records_protocol"] == protocol
    assert json.loads((tmp_path / "metrics.json").read_text()) == report
    table = (tmp_path / "table.md").read_text()
    assert f"\n{report['protocol']}\n" in table and table.count("records built with") == 1
    # A dataset without a records' protocol: neither the field nor the clause.
    plain = reports.write_report(tmp_path / "plain", results, height=48, width=64)
    assert "records_protocol" not in plain and "records built" not in plain["protocol"]


def test_report_counts_the_pixels_each_method_had_excluded(tmp_path):
    nan = float("nan")
    results = {
        # Pair 1 had 30 of its 100 valid pixels excluded; pair 2 had no scored pixel.
        "other": (
            {
                "abs_inv": np.array([0.02, 0.04, nan]),
                "abs_rel": np.array([0.1, 0.2, nan]),
                "s_rmse": np.array([0.1, 0.1, nan]),
                "num_pixels": np.array([100.0, 70.0, 0.0]),
                "excluded_pixels": np.array([0.0, 30.0, 100.0]),
                "example_mask": np.array([True, True, True]),
            },
            ["pair/0", "pair/1", "pair/2"],
        ),
        "dataset_mean": (
            {
                "abs_inv": np.array([0.03, 0.05, 0.04]),
                "abs_rel": np.array([0.1, 0.2, 0.3]),
                "s_rmse": np.array([0.1, 0.1, 0.1]),
                "num_pixels": np.array([100.0, 100.0, 100.0]),
                "excluded_pixels": np.zeros(3),
                "example_mask": np.array([True, True, True]),
            },
            ["pair/0", "pair/1", "pair/2"],
        ),
    }
    report = reports.write_report(
        tmp_path, results, height=48, width=64, protocol_note="stored predictions from x"
    )
    # The errors average over the two scored pairs; the pixel counts over all three.
    assert report["methods"]["other"]["abs_inv"]["mean"] == pytest.approx(0.03)
    assert report["methods"]["other"]["abs_inv"]["count"] == 2
    assert report["excluded_pixels"] == {
        "other": {
            "pixels": 130,
            "valid_pixels": 300,
            "fraction": pytest.approx(130 / 300),
            "per_example": pytest.approx(130 / 3),
            "unscored_examples": 1,
        },
        "dataset_mean": {
            "pixels": 0,
            "valid_pixels": 300,
            "fraction": 0.0,
            "per_example": 0.0,
            "unscored_examples": 0,
        },
    }
    assert report["protocol"].endswith("no median scaling; stored predictions from x")
    table = (tmp_path / "table.md").read_text()
    assert (
        "Excluded pixels (valid ground truth, prediction not finite or not positive): other 130 "
        "of 300 (43.33%), 1 example(s) without a scored pixel left out of its means.\n" in table
    )
    with (tmp_path / "per_example_other.csv").open() as stream:
        rows = list(csv.DictReader(stream))
    assert [row["abs_inv"] for row in rows] == ["0.02", "0.04", "nan"]
    assert [row["excluded_pixels"] for row in rows] == ["0", "30", "100"]


def test_report_counts_failed_pairs_and_keeps_no_row_of_an_earlier_report(tmp_path):
    mean, mean_ids = _per_example([0.04, 0.04, 9.0], [True, True, False])
    sfm, sfm_ids = _per_example([0.01, 0.04, 9.0], [True, True, False])
    # The classical pipeline failed on the second pair (and on the padding row).
    sfm["failed"] = np.array([0.0, 1.0, 1.0])
    results = {"dataset_mean": (mean, mean_ids), "sfm_flow": (sfm, sfm_ids)}
    report = reports.write_report(tmp_path, results, height=48, width=64)
    assert report["labels"] == {"sfm_flow": "classical pipeline on the same flow (no training)"}
    assert report["abs_inv_vs_dataset_mean"]["sfm_flow"] == pytest.approx(0.625)
    lines = (tmp_path / "table.md").read_text().splitlines()
    assert lines[3].startswith(SFM_ROW) and lines[3].endswith("| 0.62× |")
    assert lines[-1] == (
        "Failed pairs (predicted as the method's fallback constant): sfm_flow 1 of 2."
    )

    # Rewritten without the row: its per-example file goes with it.
    reports.write_report(tmp_path, {"dataset_mean": (mean, mean_ids)}, height=48, width=64)
    assert [path.name for path in tmp_path.glob("per_example_*.csv")] == [
        "per_example_dataset_mean.csv"
    ]
    assert "Failed pairs" not in (tmp_path / "table.md").read_text()


def test_example_figures_are_written_one_per_example(tmp_path):
    rng = np.random.default_rng(0)
    examples = [
        {
            "id": f"scene/{index}",
            "image1": rng.uniform(-0.5, 0.5, (12, 16, 3)).astype(np.float32),
            "depth": rng.uniform(1.0, 4.0, (12, 16)).astype(np.float32),
            "depth_valid": np.ones((12, 16), bool),
            "sparse_mask": np.eye(12, 16, dtype=bool),
        }
        for index in range(2)
    ]
    predictions = [np.full((12, 16), 2.0, np.float32)] * 2
    paths = reports.render_examples(tmp_path, examples, predictions)
    assert [path.name for path in paths] == ["scene_0.png", "scene_1.png"]
    assert all(path.stat().st_size > 1000 for path in paths)
