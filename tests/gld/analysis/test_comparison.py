"""`gld.analysis.comparison`: a finished run is reused and tabulated with the references,
scored against the truth it is given (the launcher's end-to-end tests, at the records'
resolution, are tests/experiments/test_compare.py)."""

import json
import shutil

import numpy as np
import pytest
from conftest import TINY_MODEL

from gld import input_pipeline
from gld.analysis import comparison
from gld.evaluation import trained_run
from gld.models import registry
from gld.runs import workdir as workdir_lib

# The trained_workdir fixture's run: 2 steps at batch 4.
TRAIN_CONFIG = {"batch_size": 4, "steps": 2, "log_every": 1, "eval_every": 0}


def _compare(tiny_scenes, workdir, messages, **options):
    return comparison.run_comparison(
        workdir=workdir,
        dataset="gld_scenes/tiny",
        train_source=tiny_scenes.as_data_source("train"),
        eval_source=tiny_scenes.as_data_source("test"),
        height=48,
        width=64,
        train_config=TRAIN_CONFIG,
        max_examples=4,
        print_fn=messages.append,
        **options,
    )


def test_a_finished_run_is_reused_and_scored_with_the_references_against_the_truth_given(
    tiny_scenes, trained_workdir, tmp_path
):
    workdir = tmp_path / "compare"
    shutil.copytree(trained_workdir, workdir / "global_local")
    messages = []
    # As experiments.compare gives a demon/* dataset's DeMoN files (here: a stand-in).
    truth = _TwiceAsFar(tiny_scenes.as_data_source("test"))
    protocol = {"image_decoder": "demon", "depth_resampling": "demon", "order": "demon"}
    report = _compare(
        tiny_scenes,
        workdir,
        messages,
        models=["global_local"],
        classical_methods=[],
        model_configs={"global_local": TINY_MODEL},
        truth=truth,
        records_protocol=protocol,
    )
    run_dir = workdir / "global_local"
    assert f"global_local: reusing the finished run in {run_dir} (step 2)" in messages
    assert list(report["methods"]) == [
        "global_local",
        "dataset_mean",
        "oracle_pair_median",
        "sfm_flow",
    ]
    for name, summary in report["methods"].items():
        assert summary["abs_inv"]["count"] == 4, name
    _, variables, _ = workdir_lib.load_trained(run_dir)
    parameters = registry.parameter_counts(variables["params"])["total"]
    assert report["runs"]["global_local"] == {
        "workdir": str(run_dir),
        "parameters": parameters,
        "steps": 2,
        "batch_size": 4,
        "train_seconds": None,
    }
    assert "2 steps at batch 4" in report["protocol"]
    assert json.loads((workdir / "compare" / "results.json").read_text()) == report
    table = (workdir / "compare" / "table.md").read_text().splitlines()
    assert f"| global_local | {parameters:,} | 2 | reused | — |" in table
    assert "| dataset_mean | 0 | 0 | none | — |" in table

    # Scored against the truth given, checked first, and stamped as such.
    assert len(truth.checked) == 4
    assert report["truth_resolution"] == "file" and report["truth_resolutions"] == {"128x96": 4}
    assert report["truth_files"] == "twice_as_far" and report["records_protocol"] == protocol
    assert "ground truth at the source files' resolution (4 at 128x96)" in report["protocol"]
    assert report["protocol"].endswith(
        "order=demon (DeMoN's reader's: files as listed, each file's scene groups reverse-sorted)"
    )
    assert report["protocol"] in table
    # The oracle takes its constant from the truth it is scored on (each pair's median
    # inverse depth of that truth), by hand:
    errors = []
    for depth, valid in truth.maps(truth.checked):
        inv_depth = 1.0 / depth[valid].astype(np.float64)
        errors.append(np.abs(inv_depth - np.median(inv_depth)).mean())
    oracle = report["methods"]["oracle_pair_median"]["abs_inv"]
    assert oracle["mean"] == pytest.approx(np.mean(errors), rel=1e-5)
    # The learned model gets the numbers experiments.evaluate gives it against that truth.
    evaluated = trained_run.evaluate_workdir(
        run_dir,
        tiny_scenes.as_data_source("test"),
        height=48,
        width=64,
        max_examples=4,
        num_figures=0,
        with_dataset_mean=False,
        with_oracle=False,
        with_sfm_flow=False,
        truth=truth,
        print_fn=lambda _: None,
    )
    for metric, summary in evaluated["methods"]["global_local"].items():
        assert report["methods"]["global_local"][metric] == pytest.approx(summary), metric


def test_unknown_methods_are_refused_before_anything_runs(tmp_path):
    def compare(models, classical_methods):
        comparison.run_comparison(
            workdir=tmp_path,
            dataset="gld_scenes/tiny",
            train_source=None,
            eval_source=None,
            height=48,
            width=64,
            models=models,
            classical_methods=classical_methods,
            train_config={},
        )

    with pytest.raises(ValueError, match="unknown model 'resnet'"):
        compare(["resnet"], [])
    with pytest.raises(ValueError, match="unknown classical method 'stereo'"):
        compare([], ["stereo"])
    assert not any(tmp_path.iterdir())


class _TwiceAsFar:
    """Ground truth at twice the records' resolution and twice their depth (each record
    pixel repeated 2 x 2), looked up by id as DeMoN's files are; `broken` fails the check."""

    def __init__(self, source, broken=False):
        self.broken, self.checked, self._maps = broken, [], {}
        for batch in input_pipeline.eval_batches(source, batch_size=16):
            for example_id, depth, valid in zip(
                batch["id"], batch["depth"], batch["depth_valid"], strict=True
            ):
                repeated = lambda field: np.repeat(np.repeat(field, 2, 0), 2, 1)  # noqa: E731
                self._maps[str(example_id)] = (repeated(2 * depth), repeated(valid))

    def check(self, examples):
        if self.broken:
            raise ValueError("the files are not those the records were built from")
        self.checked = [example_id for example_id, _ in examples]

    def shapes(self):
        return {example_id: self._maps[example_id][0].shape for example_id in self.checked}

    def maps(self, ids):
        assert set(ids) <= set(self.checked), "looked up before the check"
        return [self._maps[example_id] for example_id in ids]

    def summary(self):
        return {"truth_files": "twice_as_far"}


def test_a_truth_that_cannot_serve_the_examples_stops_the_comparison_before_training(
    tiny_scenes, tmp_path
):
    broken = _TwiceAsFar(tiny_scenes.as_data_source("test"), broken=True)
    with pytest.raises(ValueError, match="not those the records were built from"):
        _compare(
            tiny_scenes,
            tmp_path,
            [],
            models=["global_local"],
            classical_methods=[],
            model_configs={"global_local": TINY_MODEL},
            truth=broken,
        )
    assert not any(tmp_path.iterdir())
