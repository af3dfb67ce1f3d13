"""`python -m experiments.regimes` end to end in a subprocess, on the tiny benchmark and a
hand-written evaluation: per-pair CSV, summary and figure; bad input named in one line."""

import csv
import json
import re

import numpy as np
import pytest
from conftest import launch, tiny_train_config

from gld import contract


def _launch(*args):
    return launch("experiments.regimes", *args, timeout=300)


@pytest.fixture
def evaluated_workdir(tiny_scenes, tmp_path):
    """A workdir of gld_scenes/tiny with an evaluation written by hand: the model's Abs-Inv
    is 1 on even test pairs and 3 on odd ones, sfm_flow's 2 on all."""
    from gld.runs import workdir as workdir_lib

    workdir = tmp_path / "run"
    workdir_lib.write_run_config(workdir, tiny_train_config())
    eval_dir = workdir / "eval"
    eval_dir.mkdir()
    metrics = {"dataset": tiny_scenes.info.full_name, "split": "test", "model": "global_local"}
    (eval_dir / "metrics.json").write_text(json.dumps({**metrics, "flow_source": "estimated"}))
    source = tiny_scenes.as_data_source("test")
    examples = [contract.decode_example(source[index]) for index in range(len(source))]
    ids = sorted(example["id"] for example in examples)
    for method, abs_inv in (("global_local", [1.0, 3.0]), ("sfm_flow", [2.0, 2.0])):
        with (eval_dir / f"per_example_{method}.csv").open("w", newline="") as file:
            writer = csv.writer(file)
            writer.writerow(["id", "abs_inv"])
            writer.writerows([example_id, abs_inv[i % 2]] for i, example_id in enumerate(ids))
    return workdir, {example["id"]: example for example in examples}


def test_writes_the_table_the_summary_and_the_figure(evaluated_workdir, tiny_scenes_dir, tmp_path):
    workdir, examples = evaluated_workdir
    out = tmp_path / "regimes"
    result = _launch(f"--workdir={workdir}", f"--data_dir={tiny_scenes_dir}", f"--output_dir={out}")
    assert result.returncode == 0, result.stderr[-3000:]
    with (out / "regimes.csv").open() as file:
        rows = list(csv.DictReader(file))
    assert len(rows) == len(examples) == 16
    for row in rows:
        example = examples[row["id"]]
        assert float(row["baseline"]) == pytest.approx(np.linalg.norm(example["translation"]))
        assert row["texture_kind"] in ("plain", "checker", "stripes", "gradient", "noise")
        assert 0 < float(row["texture_share"]) <= 1
        assert float(row["ratio"]) in (0.5, 1.5)
    summary = (out / "regimes.md").read_text()
    assert "| all pairs |  | all | 16 | 2.0000 | 2.0000 | 1.00× | 50% |" in summary
    assert "| texture kind |" in summary
    assert summary in result.stdout
    assert (out / "regimes.png").read_bytes()[:4] == b"\x89PNG"


def test_bad_input_is_named(evaluated_workdir, tiny_scenes_dir, tmp_path):
    workdir, _ = evaluated_workdir
    out = tmp_path / "out"
    (workdir / "eval" / "per_example_sfm_flow.csv").rename(tmp_path / "kept.csv")
    cases = [
        ([f"--workdir={tmp_path / 'missing'}"], r"--workdir: .*missing.*config\.json not found"),
        ([f"--workdir={workdir}"], r"per_example_sfm_flow\.csv not found: evaluate first"),
        (
            [
                f"--workdir={workdir}",
                f"--eval_dir={workdir / 'eval'}",
                "--dataset=gld_scenes/tiny_untextured",
            ],
            r"evaluates gld_scenes/tiny/2\.0\.0, not --dataset=gld_scenes/tiny_untextured",
        ),
    ]
    for args, message in cases:
        result = _launch(*args, f"--data_dir={tiny_scenes_dir}", f"--output_dir={out}")
        assert result.returncode != 0, args
        assert re.search(message, result.stderr), (message, result.stderr[-2000:])
        assert not out.exists(), args
