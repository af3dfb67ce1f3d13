"""Regimes over an evaluation (gld/analysis/regimes_run.py): the evaluation is found and
checked, by the flags' names, before the dataset is read or a file written. The run on
the tiny benchmark: tests/experiments/test_regimes_launcher.py."""

import json
from types import SimpleNamespace

import pytest
from conftest import tiny_train_config

from gld.analysis import regimes_run
from gld.arguments import ArgumentError
from gld.runs import workdir as workdir_lib

EVALUATED = "gld_scenes/tiny/2.0.0"


def _evaluated(tmp_path, model="global_local", rows=None):
    """A workdir of gld_scenes/tiny whose eval/ evaluates `model`; per-example CSVs of the
    model and sfm_flow, with `rows` ({method: csv text}, default: the same two pairs)."""
    workdir = tmp_path / "run"
    workdir_lib.write_run_config(workdir, tiny_train_config())
    eval_dir = workdir / "eval"
    eval_dir.mkdir()
    (eval_dir / "metrics.json").write_text(json.dumps({"dataset": EVALUATED, "model": model}))
    rows = rows or {method: "id,abs_inv\na,1\nb,2\n" for method in (model, "sfm_flow")}
    for method, text in rows.items():
        (eval_dir / f"per_example_{method}.csv").write_text(text)
    return workdir


def _refused(workdir, output_dir, message, **arguments):
    def get_builder(name):
        return SimpleNamespace(is_prepared=lambda: False, data_dir="nowhere")

    with pytest.raises(ArgumentError, match=message):
        regimes_run.write_regimes(
            workdir,
            output_dir,
            get_builder=arguments.pop("get_builder", get_builder),
            texture_reader=lambda builder: None,
            **arguments,
        )
    assert not output_dir.exists()


def test_the_evaluation_is_found_and_checked(tmp_path):
    out = tmp_path / "out"
    _refused(tmp_path / "missing", out, r"--workdir: .*missing.*config\.json not found")
    workdir = _evaluated(tmp_path)
    metrics = workdir / "eval_gld_scenes-tiny_untextured" / "metrics.json"
    _refused(
        workdir,
        out,
        rf"{metrics} not found: evaluate {workdir} on gld_scenes/tiny_untextured first",
        dataset="gld_scenes/tiny_untextured",
    )
    _refused(
        workdir,
        out,
        rf"evaluates {EVALUATED}, not --dataset=gld_scenes/tiny_untextured",
        dataset="gld_scenes/tiny_untextured",
        eval_dir=workdir / "eval",
    )
    _refused(workdir, out, "evaluates global_local itself", reference="global_local")
    _refused(
        workdir,
        out,
        r"per_example_oracle\.csv not found: evaluate first \(python -m "
        rf"experiments\.evaluate --workdir={workdir}\)",
        reference="oracle",
    )
    _refused(workdir, out, f"{EVALUATED} is not built under nowhere")
    built_other = SimpleNamespace(
        is_prepared=lambda: True, info=SimpleNamespace(full_name="gld_scenes/tiny/1.0.0")
    )
    _refused(
        workdir,
        out,
        f"evaluates {EVALUATED}; gld_scenes/tiny/1.0.0 is built",
        get_builder=lambda name: built_other,
    )


def test_the_two_methods_must_be_scored_on_the_same_pairs(tmp_path):
    rows = {"global_local": "id,abs_inv\na,1\n", "sfm_flow": "id,abs_inv\na,2\nb,2\n"}
    workdir = _evaluated(tmp_path, rows=rows)
    _refused(workdir, tmp_path / "out", "global_local and sfm_flow were scored on other pairs")
    rows = {"global_local": "id,abs_inv\na,1\n", "sfm_flow": "id,depth\na,2\n"}
    workdir = _evaluated(tmp_path / "columns", rows=rows)
    _refused(workdir, tmp_path / "out", "per_example_sfm_flow.csv has no id and abs_inv columns")
