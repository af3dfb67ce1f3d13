"""A suite's training runs: what a run's result reads from its metrics log, and whether a
retrained run scores its result."""

import json

import pytest

from gld.paper import training_runs


def test_curves_and_training_time_from_the_metrics_log(tmp_path):
    lines = [
        {"step": 50, "split": "train", "depth_l1": 0.05, "grad_norm": 0.3, "steps_per_sec": 5.0},
        {"step": 100, "split": "train", "depth_l1": 0.04, "steps_per_sec": 2.5},
        {"step": 100, "split": "test", "abs_inv": 0.03, "abs_rel": 0.4, "s_rmse": 0.3},
        {"step": 150, "split": "train", "loss": 1.0},  # a self-supervised run's record
    ]
    (tmp_path / "metrics.jsonl").write_text("\n".join(json.dumps(line) for line in lines))
    curves, seconds = training_runs._training_log(tmp_path)
    assert curves == {
        "train": [[50, 0.05], [100, 0.04]],
        "loss": [[150, 1.0]],
        "grad_norm": [[50, 0.3]],
        "test": [[100, 0.03]],
    }
    assert seconds == pytest.approx(50 / 5.0 + 50 / 2.5)


def test_a_retrained_run_is_compared_with_its_result():
    assert training_runs._reproduction("run", [0.1, 0.2], [0.1, 0.2 + 1e-9]) is None
    difference = training_runs._reproduction("run", [0.1, 0.2], [0.1, 0.21])
    assert difference.startswith("run retrained scores 0.155, its result 0.15:")
    assert training_runs._reproduction("run", [0.1, 0.2], [0.1]) is not None
