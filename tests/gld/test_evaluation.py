"""Tests of the evaluation reports (gld/evaluation.py): every table carries its references."""

import csv
import json

import numpy as np
import pytest
from conftest import tiny_train_config

from gld import evaluation, input_pipeline, train
from gld import model as model_lib

ORACLE_ROW = "| oracle_pair_median — per-pair oracle constant (sees the truth) |"


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
    report = evaluation.write_report(tmp_path, results, height=48, width=64, info={"split": "x"})

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


def _oracle_abs_inv_by_hand(source) -> list[float]:
    """Each test pair's mean |1/d - median(1/d)| over its valid pixels, in numpy."""
    errors = []
    for batch in input_pipeline.eval_batches(source, batch_size=16, flow_source="gt"):
        for depth, valid, real in zip(
            batch["depth"], batch["depth_valid"], batch["example_mask"], strict=True
        ):
            if real:
                inv_depth = 1.0 / depth[valid].astype(np.float64)
                errors.append(float(np.abs(inv_depth - np.median(inv_depth)).mean()))
    return errors


def test_a_classical_method_is_reported_with_the_dataset_mean_and_the_oracle(tiny_scenes, tmp_path):
    source = tiny_scenes.as_data_source("test")
    printed = []
    report = evaluation.evaluate_workdir(
        tmp_path,
        source,
        train_source=tiny_scenes.as_data_source("train"),
        height=48,
        width=64,
        num_figures=0,
        classical_method="triangulation_gt_pose",
        flow="gt",
        print_fn=printed.append,
    )
    methods = report["methods"]
    assert list(methods) == ["triangulation_gt_pose", "dataset_mean", "oracle_pair_median"]
    for name, summary in methods.items():
        assert summary["abs_inv"]["count"] == 16, name

    # The oracle is each pair's median truth: its per-pair errors follow by hand.
    with (tmp_path / "eval" / "per_example_oracle_pair_median.csv").open() as stream:
        oracle_errors = [float(row["abs_inv"]) for row in csv.DictReader(stream)]
    np.testing.assert_allclose(oracle_errors, _oracle_abs_inv_by_hand(source), rtol=1e-4)
    # The best constant of each pair beats the one constant of all pairs.
    oracle, mean = (methods[n]["abs_inv"]["mean"] for n in ("oracle_pair_median", "dataset_mean"))
    assert oracle < mean
    assert report["abs_inv_vs_dataset_mean"]["oracle_pair_median"] == pytest.approx(oracle / mean)

    table = (tmp_path / "eval" / "table.md").read_text()
    assert printed == [table]
    assert ORACLE_ROW in table and "| dataset_mean |" in table and "1.00×" in table


def test_the_oracle_alone_is_evaluated_once(tiny_scenes, tmp_path):
    report = evaluation.evaluate_workdir(
        tmp_path,
        tiny_scenes.as_data_source("test"),
        height=48,
        width=64,
        num_figures=0,
        classical_method="oracle_pair_median",
        max_examples=4,
        print_fn=lambda _: None,
    )
    # No training split given: no dataset mean, hence no ratio column.
    assert list(report["methods"]) == ["oracle_pair_median"]
    assert report["methods"]["oracle_pair_median"]["abs_inv"]["count"] == 4
    assert report["abs_inv_vs_dataset_mean"] == {}
    assert ORACLE_ROW in (tmp_path / "eval" / "table.md").read_text()


@pytest.fixture
def untrained_workdir(tiny_scenes, tmp_path):
    """A workdir whose only checkpoint (step 0) holds the tiny model's initial state."""
    config = tiny_train_config()
    workdir = tmp_path / "run"
    workdir.mkdir()
    train.write_run_config(workdir, config)
    model = model_lib.make_model(config.model, **config.model_config)
    state = train.create_train_state(
        model, train.make_optimizer(config.learning_rate), config.height, config.width, 0
    )
    iterator = iter(
        input_pipeline.train_dataset(
            tiny_scenes.as_data_source("train"), batch_size=4, seed=0, gt_pixels=1
        )
    )
    manager = train.checkpoint_manager(workdir)
    train.save_checkpoint(manager, state, iterator)
    manager.wait_until_finished()
    manager.close()
    return workdir


def test_a_model_is_reported_with_the_dataset_mean_and_the_oracle(tiny_scenes, untrained_workdir):
    report = evaluation.evaluate_workdir(
        untrained_workdir,
        tiny_scenes.as_data_source("test"),
        train_source=tiny_scenes.as_data_source("train"),
        height=48,
        width=64,
        num_figures=0,
        print_fn=lambda _: None,
    )
    assert list(report["methods"]) == ["global_local", "dataset_mean", "oracle_pair_median"]
    assert report["step"] == 0
    ratios = report["abs_inv_vs_dataset_mean"]
    assert set(ratios) == set(report["methods"]) and ratios["dataset_mean"] == 1.0
    means = {name: summary["abs_inv"]["mean"] for name, summary in report["methods"].items()}
    for name in ("global_local", "oracle_pair_median"):
        assert ratios[name] == pytest.approx(means[name] / means["dataset_mean"]), name
    assert report["methods"]["global_local"]["abs_inv"]["count"] == 16
    lines = (untrained_workdir / "eval" / "table.md").read_text().splitlines()
    assert lines[2].startswith("| global_local |")
    assert lines[2].endswith(f"| {ratios['global_local']:.2f}× |")
    assert lines[4].startswith(ORACLE_ROW)
