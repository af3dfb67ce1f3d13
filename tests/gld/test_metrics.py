import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from gld import metrics


def test_depth_metrics_by_hand():
    truth = jnp.array([[[1.0, 2.0], [4.0, 0.0]]])
    prediction = jnp.array([[[2.0, 2.0], [2.0, 7.0]]])
    valid = truth > 0
    result = jax.jit(metrics.depth_metrics)(prediction, truth, valid)
    assert float(result["abs_inv"][0]) == pytest.approx((0.5 + 0 + 0.25) / 3)
    assert float(result["abs_rel"][0]) == pytest.approx((1.0 + 0 + 0.5) / 3)
    log_errors = np.log([1 / 2, 1.0, 2.0])
    expected = math.sqrt(np.mean(log_errors**2) - np.mean(log_errors) ** 2)
    assert float(result["s_rmse"][0]) == pytest.approx(expected, rel=1e-5)
    assert float(result["num_pixels"][0]) == 3


def test_scale_invariant_rmse_ignores_a_global_scale_but_others_do_not():
    truth = jnp.asarray(np.random.default_rng(0).uniform(1, 5, (1, 4, 4)), jnp.float32)
    valid = jnp.ones_like(truth, bool)
    result = metrics.depth_metrics(truth * 3.0, truth, valid)
    assert float(result["s_rmse"][0]) == pytest.approx(0.0, abs=1e-3)
    assert float(result["abs_rel"][0]) == pytest.approx(2.0, rel=1e-5)


def test_examples_without_valid_pixels_are_marked_and_summary_ignores_padding():
    truth = jnp.zeros((1, 2, 2))
    result = metrics.depth_metrics(jnp.ones((1, 2, 2)), truth, truth > 0)
    assert float(result["num_pixels"][0]) == 0
    summary = metrics.summarise(
        {"abs_inv": np.array([1.0, 3.0, 100.0])}, np.array([True, True, False])
    )
    assert summary["abs_inv"] == {"mean": 2.0, "std": 1.0, "count": 2}


def test_pose_errors():
    rotation = np.eye(3)[None]
    errors = metrics.pose_errors(
        rotation, np.array([[0, 0, 1.0]]), rotation, np.array([[0, 1, 0.0]])
    )
    assert float(errors["rotation_deg"][0]) == pytest.approx(0.0, abs=1e-5)
    assert float(errors["translation_deg"][0]) == pytest.approx(90.0)


def test_table_carries_the_protocol_stamp():
    summary = {name: {"mean": 0.5, "std": 0.1, "count": 2} for name in metrics.DEPTH_METRICS}
    stamp = metrics.protocol_stamp(192, 256, 2)
    table = metrics.markdown_table([("global_local", summary)], stamp)
    assert "| global_local | 0.5000 ± 0.1000 |" in table
    assert "256x192" in table and "||t|| = 1" in table and "no median scaling" in table


def _summary(abs_inv: float) -> dict[str, dict]:
    return {
        name: {"mean": abs_inv if name == "abs_inv" else 0.5, "std": 0.1, "count": 2}
        for name in metrics.DEPTH_METRICS
    }


def test_table_gives_abs_inv_as_a_multiple_of_the_dataset_mean():
    rows = [
        ("global_local", _summary(0.03)),
        ("dataset_mean", _summary(0.04)),
        ("oracle_pair_median", _summary(0.01)),
    ]
    assert metrics.ratios_to_reference(rows) == pytest.approx(
        {"global_local": 0.75, "dataset_mean": 1.0, "oracle_pair_median": 0.25}
    )
    table = metrics.markdown_table(
        rows, "stamp", labels={"oracle_pair_median": "per-pair oracle constant"}
    )
    lines = table.splitlines()
    assert lines[0] == "| method | Abs-Inv | Abs-Rel | S-RMSE | Abs-Inv ÷ dataset_mean |"
    assert lines[1] == "|---|---|---|---|---|"
    assert lines[2].startswith("| global_local | 0.0300 ± 0.1000 |")
    assert lines[2].endswith("| 0.75× |")
    assert lines[3].endswith("| 1.00× |")
    assert lines[4].startswith("| oracle_pair_median — per-pair oracle constant | 0.0100")
    assert lines[4].endswith("| 0.25× |")


def test_table_without_the_reference_has_no_ratio_column():
    assert metrics.ratios_to_reference([("global_local", _summary(0.03))]) == {}
    assert metrics.ratios_to_reference([("dataset_mean", _summary(0.0))]) == {}
    table = metrics.markdown_table([("global_local", _summary(0.03))], "stamp")
    assert table.splitlines()[0] == "| method | Abs-Inv | Abs-Rel | S-RMSE |"
