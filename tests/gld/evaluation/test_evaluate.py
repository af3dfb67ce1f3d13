"""The evaluation loop and a workdir's evaluation (gld/evaluation/evaluate.py): every table
carries its references."""

import csv
import json
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
from conftest import run_python, tiny_train_config

from gld import input_pipeline, records
from gld.evaluation import evaluate as evaluation
from gld.evaluation import stored_predictions, trained_run
from gld.models import layers, registry
from gld.models.baselines import classical
from gld.runs import checkpoints as checkpoint_lib
from gld.runs import state as state_lib
from gld.runs import workdir as workdir_lib
from gld.runs.optimizer import make_optimizer

ORACLE_ROW = "| oracle_pair_median — per-pair oracle constant (sees the truth) |"
SFM_ROW = "| sfm_flow — classical pipeline on the same flow (no training) |"
REFERENCES = ["dataset_mean", "oracle_pair_median", "sfm_flow"]


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


def test_a_classical_method_is_reported_with_the_references(tiny_scenes, tmp_path):
    source = tiny_scenes.as_data_source("test")
    printed = []
    report = trained_run.evaluate_workdir(
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
    assert list(methods) == ["triangulation_gt_pose", *REFERENCES]
    for name, summary in methods.items():
        assert summary["abs_inv"]["count"] == 16, name
    # The classical pipeline runs on the same (true) flow, which fixes the pose: it is
    # near exact, far from what it gets from the estimated flow.
    assert methods["sfm_flow"]["abs_inv"]["mean"] < 0.1 * methods["dataset_mean"]["abs_inv"]["mean"]
    assert report["sfm_flow_fallback_inv_depth"] == report["dataset_mean_inv_depth"]

    # The oracle is each pair's median truth: its per-pair errors follow by hand.
    with (tmp_path / "eval_flow-gt" / "per_example_oracle_pair_median.csv").open() as stream:
        oracle_errors = [float(row["abs_inv"]) for row in csv.DictReader(stream)]
    np.testing.assert_allclose(oracle_errors, _oracle_abs_inv_by_hand(source), rtol=1e-4)
    # The best constant of each pair beats the one constant of all pairs.
    oracle, mean = (methods[n]["abs_inv"]["mean"] for n in ("oracle_pair_median", "dataset_mean"))
    assert oracle < mean
    assert report["abs_inv_vs_dataset_mean"]["oracle_pair_median"] == pytest.approx(oracle / mean)

    table = (tmp_path / "eval_flow-gt" / "table.md").read_text()
    assert printed == [table]
    assert ORACLE_ROW in table and "| dataset_mean |" in table and "1.00×" in table
    assert SFM_ROW in table and "Failed pairs (predicted as the method's fallback" in table


def test_the_oracle_alone_is_evaluated_once(tiny_scenes, tmp_path):
    report = trained_run.evaluate_workdir(
        tmp_path,
        tiny_scenes.as_data_source("test"),
        height=48,
        width=64,
        num_figures=0,
        classical_method="oracle_pair_median",
        max_examples=4,
        print_fn=lambda _: None,
    )
    # No training split given: no dataset mean, hence no ratio column; the classical
    # pipeline's failed pairs fall back to a fixed constant, which metrics.json says.
    assert list(report["methods"]) == ["oracle_pair_median", "sfm_flow"]
    for summary in report["methods"].values():
        assert summary["abs_inv"]["count"] == 4
    assert report["abs_inv_vs_dataset_mean"] == {}
    assert report["sfm_flow_fallback"] == "a fixed constant (no training split)"
    assert report["sfm_flow_fallback_inv_depth"] == layers.INITIAL_INV_DEPTH
    table = (tmp_path / "eval_first4" / "table.md").read_text()
    assert ORACLE_ROW in table and SFM_ROW in table


@pytest.fixture(scope="module")
def untrained_run(tiny_scenes, tmp_path_factory):
    """A workdir whose only checkpoint (step 0) holds the tiny model's initial state."""
    config = tiny_train_config()
    workdir = tmp_path_factory.mktemp("untrained") / "run"
    workdir.mkdir()
    workdir_lib.write_run_config(workdir, config)
    model = registry.make_model(config.model, **config.model_config)
    state = state_lib.create_train_state(
        model, make_optimizer(config.learning_rate), config.height, config.width, 0
    )
    iterator = iter(
        input_pipeline.train_dataset(
            tiny_scenes.as_data_source("train"), batch_size=4, seed=0, gt_pixels=1
        )
    )
    manager = checkpoint_lib.checkpoint_manager(workdir)
    checkpoint_lib.save_checkpoint(manager, state, iterator)
    manager.wait_until_finished()
    manager.close()
    return workdir


@pytest.fixture
def untrained_workdir(untrained_run, tmp_path):
    """A copy of `untrained_run` for one test, which writes its evaluations there."""
    return Path(shutil.copytree(untrained_run, tmp_path / "run"))


def test_a_model_is_reported_with_the_references(tiny_scenes, untrained_workdir):
    report = trained_run.evaluate_workdir(
        untrained_workdir,
        tiny_scenes.as_data_source("test"),
        train_source=tiny_scenes.as_data_source("train"),
        height=48,
        width=64,
        num_figures=0,
        print_fn=lambda _: None,
    )
    assert list(report["methods"]) == ["global_local", *REFERENCES]
    assert report["step"] == 0
    ratios = report["abs_inv_vs_dataset_mean"]
    assert set(ratios) == set(report["methods"]) and ratios["dataset_mean"] == 1.0
    means = {name: summary["abs_inv"]["mean"] for name, summary in report["methods"].items()}
    for name in ("global_local", "oracle_pair_median", "sfm_flow"):
        assert ratios[name] == pytest.approx(means[name] / means["dataset_mean"]), name
    for name, summary in report["methods"].items():
        assert summary["abs_inv"]["count"] == 16, name
    assert report["labels"]["sfm_flow"] == "classical pipeline on the same flow (no training)"
    lines = (untrained_workdir / "eval" / "table.md").read_text().splitlines()
    assert lines[2].startswith("| global_local |")
    assert lines[2].endswith(f"| {ratios['global_local']:.2f}× |")
    assert lines[4].startswith(ORACLE_ROW)
    assert lines[5].startswith(SFM_ROW) and lines[5].endswith(f"| {ratios['sfm_flow']:.2f}× |")
    failed = report["methods"]["sfm_flow"]["failed"]
    assert f"sfm_flow {round(failed['mean'] * 16)} of 16." in lines[-1]


def _ids_and_abs_inv(path: Path) -> dict[str, float]:
    with path.open() as stream:
        return {row["id"]: float(row["abs_inv"]) for row in csv.DictReader(stream)}


@pytest.mark.parametrize("flow_source", ["gt", "estimated"])
def test_the_classical_pipeline_sees_the_examples_and_the_flow_of_the_model(
    tiny_scenes, untrained_workdir, flow_source
):
    source, train_source = (tiny_scenes.as_data_source(split) for split in ("test", "train"))
    report = trained_run.evaluate_workdir(
        untrained_workdir,
        source,
        train_source=train_source,
        height=48,
        width=64,
        num_figures=0,
        max_examples=6,
        flow_source=flow_source,
        with_dataset_mean=False,
        with_oracle=False,
        print_fn=lambda _: None,
    )
    assert list(report["methods"]) == ["global_local", "sfm_flow"]
    assert report["flow_source"] == flow_source
    # Without the dataset-mean row, the classical pipeline still falls back to its value.
    mean = trained_run.fit_classical("dataset_mean", train_source).inv_depth
    assert report["sfm_flow_fallback_inv_depth"] == mean
    folder = trained_run.evaluation_dir(
        untrained_workdir, max_examples=6, flow_source=None if flow_source == "estimated" else "gt"
    )
    model_rows = _ids_and_abs_inv(folder / "per_example_global_local.csv")
    sfm_rows = _ids_and_abs_inv(folder / "per_example_sfm_flow.csv")
    assert list(sfm_rows) == list(model_rows) and len(model_rows) == 6
    # Scored as SfMFlow on this flow scores, not as on the other one.
    expected = {}
    for flow in ("gt", "estimated"):
        method = classical.SfMFlow(fallback_inv_depth=mean)
        per_example, ids = evaluation.evaluate_predictor(
            method.predict, source, max_examples=6, flow_source=flow
        )
        expected[flow] = dict(zip(ids[:6], per_example["abs_inv"][:6], strict=True))
    assert sfm_rows == pytest.approx(expected[flow_source], rel=1e-5)
    other = "estimated" if flow_source == "gt" else "gt"
    assert sfm_rows != pytest.approx(expected[other], rel=1e-3)


def test_an_evaluation_without_the_classical_row_is_rewritten_with_it(
    tiny_scenes, untrained_workdir
):
    def evaluate(**references):
        return trained_run.evaluate_workdir(
            untrained_workdir,
            tiny_scenes.as_data_source("test"),
            height=48,
            width=64,
            num_figures=0,
            max_examples=3,
            print_fn=lambda _: None,
            **references,
        )

    folder = untrained_workdir / "eval_first3"
    # As written before the classical pipeline was a reference: no sfm_flow row.
    before = evaluate(with_sfm_flow=False)
    assert list(before["methods"]) == ["global_local", "oracle_pair_median"]
    assert "sfm_flow_fallback" not in before
    # The same evaluation again is not refused: it is rewritten, the new row included.
    after = evaluate()
    assert list(after["methods"]) == ["global_local", "oracle_pair_median", "sfm_flow"]
    assert after["methods"]["global_local"] == before["methods"]["global_local"]
    assert SFM_ROW in (folder / "table.md").read_text()
    assert (folder / "per_example_sfm_flow.csv").exists()
    # Asked without it again, no file of the row is left behind to be mixed in.
    evaluate(with_sfm_flow=False, with_oracle=False)
    assert sorted(path.name for path in folder.glob("per_example_*.csv")) == [
        "per_example_global_local.csv"
    ]
    assert json.loads((folder / "metrics.json").read_text())["methods"].keys() == {"global_local"}


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


class _DoubledTruth:
    """The records' truth at twice their resolution, each pixel repeated 2x2: a
    prediction resized to it by nearest neighbour scores as at the records'."""

    def __init__(self, source):
        self.pairs = {key: value[:2] for key, value in _test_pairs(source).items()}
        self.looked_up = []

    def check(self, examples):
        assert {example_id for example_id, _ in examples} <= set(self.pairs)

    def shapes(self):
        return {example_id: (96, 128) for example_id in self.pairs}

    def maps(self, ids):
        self.looked_up.extend(ids)
        doubled = lambda image: np.repeat(np.repeat(image, 2, 0), 2, 1)  # noqa: E731
        return [tuple(doubled(image) for image in self.pairs[example_id]) for example_id in ids]

    def summary(self):
        return {"truth_files": "doubled records"}


def test_a_truth_at_another_resolution_is_scored_in_the_same_loop(tiny_scenes, untrained_workdir):
    model, variables, _ = workdir_lib.load_trained(untrained_workdir)
    source = tiny_scenes.as_data_source("test")
    truth = _DoubledTruth(source)
    at_records, ids = evaluation.evaluate_source(
        model, variables, source, batch_size=3, max_examples=5
    )
    on_devices, device_ids = evaluation.evaluate_source(
        model, variables, source, batch_size=3, max_examples=5, truth=truth
    )
    # Padded rows are not looked up.
    assert device_ids == ids and truth.looked_up == ids[:5]

    def predict(batch):
        outputs = model.apply(variables, batch["image1"], batch["image2"], batch["flow"])
        return {"depth": outputs["depth"]}

    on_host, _ = evaluation.evaluate_predictor(
        predict, source, batch_size=3, max_examples=5, truth=truth
    )
    for scored in (on_devices, on_host):
        np.testing.assert_array_equal(scored["example_mask"], [True] * 5 + [False])
        np.testing.assert_array_equal(scored["num_pixels"][:5], 4 * at_records["num_pixels"][:5])
        for name in ("abs_inv", "abs_rel", "s_rmse"):
            np.testing.assert_allclose(scored[name][:5], at_records[name][:5], rtol=1e-5)
    with pytest.raises(ValueError, match="eval_step or truth"):
        evaluation.evaluate_source(
            model, variables, source, batch_size=3, eval_step=len, truth=truth
        )


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


def test_an_example_whose_predictions_are_all_excluded_still_counts():
    batch = {
        "depth": np.full((2, 4, 4), 2.0, np.float32),
        "depth_valid": np.ones((2, 4, 4), bool),
        "example_mask": np.array([True, True]),
    }
    depth = np.stack([np.full((4, 4), 4.0), np.zeros((4, 4))]).astype(np.float32)
    scored = evaluation.score_batch(depth, batch)
    # Its truth is valid, so it stays among the examples; its errors are NaN, not 0.
    np.testing.assert_array_equal(scored["example_mask"], [True, True])
    np.testing.assert_array_equal(scored["excluded_pixels"], [0, 16])
    assert float(scored["abs_inv"][0]) == pytest.approx(0.25) and np.isnan(scored["abs_inv"][1])


def _test_pairs(source):
    """id -> (normalised depth, valid, raw depth, ||t||) of every test pair."""
    pairs = {}
    for batch in input_pipeline.eval_batches(source, batch_size=16, flow_source="gt"):
        for example_id, depth, valid, real in zip(
            batch["id"], batch["depth"], batch["depth_valid"], batch["example_mask"], strict=True
        ):
            if real:
                pairs[str(example_id)] = [depth, valid]
    for index in range(len(source)):
        raw = records.decode(source[index])
        pairs[raw["id"]] += [raw["depth1"], float(np.linalg.norm(raw["translation"]))]
    return pairs


def _abs_inv_by_hand(prediction, depth, valid):
    scored = valid & np.isfinite(prediction) & (prediction > 0)
    return float(np.abs(1.0 / depth[scored] - 1.0 / prediction[scored].astype(np.float64)).mean())


def test_stored_predictions_are_scored_with_the_references(tiny_scenes, tmp_path):
    source = tiny_scenes.as_data_source("test")
    folder = tmp_path / "exact"
    folder.mkdir()
    for example_id, (depth, *_) in _test_pairs(source).items():
        np.save(folder / f"{stored_predictions.file_stem(example_id)}.npy", depth)
    report = trained_run.evaluate_workdir(
        tmp_path / "run",
        source,
        train_source=tiny_scenes.as_data_source("train"),
        height=48,
        width=64,
        num_figures=2,
        predictions=stored_predictions.StoredPredictions(folder),
        print_fn=lambda _: None,
    )
    assert list(report["methods"]) == ["stored_predictions", *REFERENCES]
    stored = report["methods"]["stored_predictions"]
    assert stored["abs_inv"] == {"mean": 0.0, "std": 0.0, "count": 16}
    assert stored["abs_rel"]["mean"] == 0.0 and stored["excluded_pixels"]["mean"] == 0.0
    assert report["excluded_pixels"]["stored_predictions"]["pixels"] == 0
    assert report["abs_inv_vs_dataset_mean"]["stored_predictions"] == 0.0
    assert report["predictions"] == str(folder) and report["model"] == "stored_predictions"
    assert (
        f"stored predictions from {folder} (normalised depth (||t|| = 1)): 16 at 64x48"
        in (report["protocol"])
    )
    assert len(list((tmp_path / "run" / "eval" / "figures").glob("*.png"))) == 2
    table = (tmp_path / "run" / "eval" / "table.md").read_text()
    assert "| stored_predictions | 0.0000 ± 0.0000 |" in table
    assert "prediction not finite or not positive): none." in table


def test_a_constant_stored_prediction_scores_as_the_dataset_mean(tiny_scenes, tmp_path):
    source = tiny_scenes.as_data_source("test")
    mean = trained_run.fit_classical("dataset_mean", tiny_scenes.as_data_source("train"))
    constant = float(mean.predict({"flow": np.zeros((1, 1, 1, 2))})["depth"][0, 0, 0])
    pairs = _test_pairs(source)
    for example_id in pairs:
        # At 8x6: resized to 64x48 by nearest neighbour, still the constant.
        np.save(
            tmp_path / f"{stored_predictions.file_stem(example_id)}.npy",
            np.full((6, 8), constant, np.float32),
        )
    predictions = stored_predictions.StoredPredictions(tmp_path)
    predictions.check(stored_predictions.record_ids_and_baselines(source), height=48, width=64)
    stored, ids = evaluation.evaluate_predictor(predictions.predict, source, batch_size=5)
    reference, reference_ids = evaluation.evaluate_predictor(mean.predict, source, batch_size=5)
    assert ids == reference_ids
    for name in ("abs_inv", "abs_rel", "s_rmse", "num_pixels", "example_mask"):
        np.testing.assert_array_equal(stored[name], reference[name], name)
    by_hand = [
        _abs_inv_by_hand(np.full((48, 64), constant), pairs[example_id][0], pairs[example_id][1])
        for example_id in ids[:16]
    ]
    np.testing.assert_allclose(stored["abs_inv"][:16], by_hand, rtol=1e-5)


def test_raw_png_millimetres_are_scaled_and_their_zeros_excluded(tiny_scenes, tmp_path):
    source = tiny_scenes.as_data_source("test")
    pairs = _test_pairs(source)
    folder = tmp_path / "png"
    folder.mkdir()
    expected_abs_inv, expected_excluded = {}, 0
    for index, (example_id, (depth, valid, raw_depth, baseline)) in enumerate(pairs.items()):
        # The truth in millimetres, 5-20% too far.
        millimetres = np.where(valid, raw_depth * (1.05 + 0.01 * index) * 1000, 0.0)
        assert millimetres.max() < 2**16
        millimetres = np.round(millimetres).astype(np.uint16)
        millimetres[:3] = 0  # no prediction in the top rows: excluded and counted
        cv2.imwrite(str(folder / f"{stored_predictions.file_stem(example_id)}.png"), millimetres)
        metres = (millimetres.astype(np.float64) * 0.001).astype(np.float32)
        prediction = (metres.astype(np.float64) / baseline).astype(np.float32)
        expected_abs_inv[example_id] = _abs_inv_by_hand(prediction, depth, valid)
        expected_excluded += int(valid[:3].sum())
    assert expected_excluded > 0
    report = trained_run.evaluate_workdir(
        tmp_path / "run",
        source,
        height=48,
        width=64,
        num_figures=0,
        with_oracle=False,
        predictions=stored_predictions.StoredPredictions(folder, depth_scale="raw"),
        print_fn=lambda _: None,
    )
    excluded = report["excluded_pixels"]["stored_predictions"]
    assert excluded["pixels"] == expected_excluded
    with (tmp_path / "run" / "eval" / "per_example_stored_predictions.csv").open() as stream:
        rows = {row["id"]: row for row in csv.DictReader(stream)}
    assert sorted(rows) == sorted(pairs)
    for example_id, row in rows.items():
        assert float(row["abs_inv"]) == pytest.approx(expected_abs_inv[example_id], rel=1e-5)
        assert float(row["excluded_pixels"]) == pairs[example_id][1][:3].sum()
    table = (tmp_path / "run" / "eval" / "table.md").read_text()
    assert f"stored_predictions {expected_excluded:,} of {excluded['valid_pixels']:,}" in table
    assert "raw depth divided by each pair's ||t||, 16-bit PNG values x 0.001" in table


def test_a_bad_prediction_file_stops_the_evaluation_before_anything_is_written(
    tiny_scenes, tmp_path
):
    source = tiny_scenes.as_data_source("test")
    folder = tmp_path / "predictions"
    folder.mkdir()
    for index, example_id in enumerate(_test_pairs(source)):
        depth = np.full((48, 64), 2.0, np.float32)
        depth[index % 48, 5] = np.nan if index == 3 else 2.0
        np.save(folder / f"{stored_predictions.file_stem(example_id)}.npy", depth)
    with pytest.raises(ValueError, match=r"\.npy: 1 NaN or inf value\(s\)"):
        trained_run.evaluate_workdir(
            tmp_path / "run",
            source,
            height=48,
            width=64,
            predictions=stored_predictions.StoredPredictions(folder),
            print_fn=lambda _: None,
        )
    assert not (tmp_path / "run").exists()


def test_each_evaluation_has_its_own_folder():
    assert trained_run.evaluation_dir("w") == Path("w/eval")
    assert trained_run.evaluation_dir("w", split="train", max_examples=2) == Path(
        "w/eval_train_first2"
    )
    assert trained_run.evaluation_dir(
        "w", step=500, flow_source="gt", truth_resolution="file", dataset="demon/sun3d/1.1.0"
    ) == Path("w/eval_demon-sun3d_step500_flow-gt_truth-file")


def test_an_evaluation_of_something_else_is_never_replaced(tiny_scenes, tmp_path):
    def evaluate(dataset):
        return trained_run.evaluate_workdir(
            tmp_path,
            tiny_scenes.as_data_source("test"),
            dataset=dataset,
            height=48,
            width=64,
            num_figures=0,
            classical_method="oracle_pair_median",
            max_examples=2,
            print_fn=lambda _: None,
        )

    evaluate("gld_scenes/tiny/1.0.0")
    written = (tmp_path / "eval_first2" / "metrics.json").read_text()
    evaluate("gld_scenes/tiny/1.0.0")  # the same evaluation again: replaced
    with pytest.raises(ValueError, match="dataset: 'gld_scenes/tiny/1.0.0' there vs 'other/x'"):
        evaluate("other/x")
    assert (tmp_path / "eval_first2" / "metrics.json").read_text() == written


THREE_DEVICE_SCRIPT = """
import json, sys
import data
from gld.evaluation import evaluate as evaluation
from gld.models import registry
from gld.runs import state as state_lib
source = data.get_builder("gld_scenes/tiny", sys.argv[1]).as_data_source("test")
model = registry.make_model("global_local", encoder_channels=[4, 8, 8, 8, 8])
variables = state_lib.init_variables(model, 48, 64, seed=0)
per_example, ids = evaluation.evaluate_source(model, variables, source, batch_size=16)
print(json.dumps({"rows": len(ids), "examples": int(per_example["example_mask"].sum()),
                  "ids": len(set(i for i, m in zip(ids, per_example["example_mask"]) if m))}))
"""


@pytest.mark.slow
def test_any_evaluation_batch_size_runs_on_any_number_of_devices(tiny_scenes_dir):
    # 16 does not split over 3 devices: batches of 18 with two padded rows each.
    result = run_python(THREE_DEVICE_SCRIPT, str(tiny_scenes_dir), device_count=3)
    counted = json.loads(result.stdout.strip().splitlines()[-1])
    assert counted == {"rows": 18, "examples": 16, "ids": 16}


THREE_DEVICE_WORKDIR_SCRIPT = """
import json, sys
import data
from gld.evaluation import trained_run
builder = data.get_builder("gld_scenes/tiny", sys.argv[1])
report = trained_run.evaluate_workdir(
    sys.argv[2], builder.as_data_source("test"), train_source=builder.as_data_source("train"),
    height=48, width=64, num_figures=0, batch_size=4, print_fn=lambda _: None)
print(json.dumps({name: s["abs_inv"]["count"] for name, s in report["methods"].items()}))
"""


@pytest.mark.slow
def test_the_references_count_the_examples_the_devices_count(tiny_scenes_dir, untrained_workdir):
    # On 3 devices the model's batches are padded differently from the host-side
    # references'; every row is still over the same 16 pairs.
    result = run_python(
        THREE_DEVICE_WORKDIR_SCRIPT, str(tiny_scenes_dir), str(untrained_workdir), device_count=3
    )
    counts = json.loads(result.stdout.strip().splitlines()[-1])
    assert counts == {name: 16 for name in ["global_local", *REFERENCES]}
