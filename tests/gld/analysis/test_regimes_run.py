"""Regimes over an evaluation (gld/analysis/regimes_run.py): the evaluation is found and
checked, by the flags' names, before the dataset is read or a file written. The run on
the tiny benchmark: tests/experiments/test_regimes_launcher.py."""

import json
import re
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


def _refusal(workdir, output_dir, **arguments) -> str:
    """The one-line error `write_regimes` refuses with; nothing is written."""

    def get_builder(name):
        return SimpleNamespace(is_prepared=lambda: False, data_dir="nowhere")

    with pytest.raises(ArgumentError) as refused:
        regimes_run.write_regimes(
            workdir,
            output_dir,
            get_builder=arguments.pop("get_builder", get_builder),
            texture_reader=lambda builder: None,
            **arguments,
        )
    assert not output_dir.exists()
    return str(refused.value)


def test_the_evaluation_is_found_and_checked(tmp_path):
    out = tmp_path / "out"
    assert re.search(
        r"--workdir: .*missing.*config\.json not found", _refusal(tmp_path / "missing", out)
    )
    workdir = _evaluated(tmp_path)
    metrics = workdir / "eval_gld_scenes-tiny_untextured" / "metrics.json"
    assert re.search(
        rf"{metrics} not found: evaluate {workdir} on gld_scenes/tiny_untextured first",
        _refusal(workdir, out, dataset="gld_scenes/tiny_untextured"),
    )
    assert re.search(
        rf"evaluates {EVALUATED}, not --dataset=gld_scenes/tiny_untextured",
        _refusal(workdir, out, dataset="gld_scenes/tiny_untextured", eval_dir=workdir / "eval"),
    )
    assert re.search(
        "evaluates global_local itself", _refusal(workdir, out, reference="global_local")
    )
    assert re.search(
        r"per_example_oracle\.csv not found: evaluate first \(python -m "
        rf"experiments\.evaluate --workdir={workdir}\)",
        _refusal(workdir, out, reference="oracle"),
    )
    assert re.search(f"{EVALUATED} is not built under nowhere", _refusal(workdir, out))
    built_other = SimpleNamespace(
        is_prepared=lambda: True, info=SimpleNamespace(full_name="gld_scenes/tiny/1.0.0")
    )
    assert re.search(
        f"evaluates {EVALUATED}; gld_scenes/tiny/1.0.0 is built",
        _refusal(workdir, out, get_builder=lambda name: built_other),
    )


def test_the_two_methods_must_be_scored_on_the_same_pairs(tmp_path):
    rows = {"global_local": "id,abs_inv\na,1\n", "sfm_flow": "id,abs_inv\na,2\nb,2\n"}
    workdir = _evaluated(tmp_path, rows=rows)
    assert re.search(
        "global_local and sfm_flow were scored on other pairs", _refusal(workdir, tmp_path / "out")
    )
    rows = {"global_local": "id,abs_inv\na,1\n", "sfm_flow": "id,depth\na,2\n"}
    workdir = _evaluated(tmp_path / "columns", rows=rows)
    assert re.search(
        "per_example_sfm_flow.csv has no id and abs_inv columns",
        _refusal(workdir, tmp_path / "out"),
    )
