"""The evaluation loop and a workdir's evaluation (gld/evaluation.py): every table
carries its references."""

import csv

import numpy as np
import pytest
from conftest import tiny_train_config

from gld import evaluation, input_pipeline
from gld import model as model_lib
from gld import state as state_lib
from gld import workdir as workdir_lib

ORACLE_ROW = "| oracle_pair_median — per-pair oracle constant (sees the truth) |"


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
        flow_source="gt",
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
    workdir_lib.write_run_config(workdir, config)
    model = model_lib.make_model(config.model, **config.model_config)
    state = state_lib.create_train_state(
        model, state_lib.make_optimizer(config.learning_rate), config.height, config.width, 0
    )
    iterator = iter(
        input_pipeline.train_dataset(
            tiny_scenes.as_data_source("train"), batch_size=4, seed=0, gt_pixels=1
        )
    )
    manager = workdir_lib.checkpoint_manager(workdir)
    workdir_lib.save_checkpoint(manager, state, iterator)
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


def test_a_learned_model_and_a_host_predictor_go_through_the_same_loop(
    tiny_scenes, untrained_workdir
):
    model, variables, _ = workdir_lib.load_trained(untrained_workdir)
    source = tiny_scenes.as_data_source("test")
    on_devices, device_ids = evaluation.evaluate_source(
        model, variables, source, batch_size=3, max_examples=5
    )

    def predict(batch):
        outputs = model.apply(variables, batch["image1"], batch["image2"], batch["flow"])
        return {"depth": outputs["depth"]}

    on_host, host_ids = evaluation.evaluate_predictor(predict, source, batch_size=3, max_examples=5)
    # 5 pairs in batches of 3: one padded row, masked out by the same rule in both.
    assert device_ids == host_ids and len(set(device_ids[:5])) == 5
    np.testing.assert_array_equal(on_devices["example_mask"], [True] * 5 + [False])
    np.testing.assert_array_equal(on_host["example_mask"], on_devices["example_mask"])
    for name in ("abs_inv", "abs_rel", "s_rmse", "num_pixels"):
        np.testing.assert_allclose(on_host[name][:5], on_devices[name][:5], rtol=1e-5)


def test_a_pair_without_valid_pixels_does_not_count():
    depth = np.ones((2, 4, 4), np.float32)
    batch = {
        "depth": np.full((2, 4, 4), 2.0, np.float32),
        "depth_valid": np.stack([np.ones((4, 4), bool), np.zeros((4, 4), bool)]),
        "example_mask": np.array([True, True]),
    }
    scored = evaluation.score_batch(depth, batch)
    np.testing.assert_array_equal(scored["example_mask"], [True, False])
    assert float(scored["abs_inv"][0]) == pytest.approx(0.5)
