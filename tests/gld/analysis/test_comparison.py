"""`gld.analysis.comparison`: a finished run is reused and tabulated with the references
(the launcher's end-to-end tests are tests/experiments/test_compare.py)."""

import json
import shutil

import pytest
from conftest import TINY_MODEL

from gld.analysis import comparison
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


def test_a_finished_run_is_reused_and_tabulated_with_the_references(
    tiny_scenes, trained_workdir, tmp_path
):
    workdir = tmp_path / "compare"
    shutil.copytree(trained_workdir, workdir / "global_local")
    messages = []
    report = _compare(
        tiny_scenes,
        workdir,
        messages,
        models=["global_local"],
        classical_methods=[],
        model_configs={"global_local": TINY_MODEL},
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
