"""The suite's pair-by-pair comparison of the main run with sfm_flow (`regimes`): each
result's per-pair Abs-Inv joined to its test pair, and the report's section 12 from it."""

import dataclasses
from types import SimpleNamespace

import numpy as np
import pytest
from report_checks import suite_results

from gld import contract
from gld.paper import analyses, result_files
from gld.paper import report as paper_report
from gld.paper.scales import SUITES
from gld.paper.training_runs import Data

SCALE = dataclasses.replace(SUITES["cpu"], dataset="gld_scenes/tiny")


@pytest.fixture
def compared(tiny_scenes, tmp_path):
    """The regimes analysis on gld_scenes/tiny, the main run's Abs-Inv written as 1 on the
    even test pairs and 3 on the odd ones (in the split's order), sfm_flow's 2 on all."""
    from data.gld_scenes import redraw

    test = tiny_scenes.as_data_source("test")
    data = Data(
        name=tiny_scenes.info.full_name,
        train=tiny_scenes.as_data_source("train"),
        test=test,
        height=48,
        width=64,
        texture=redraw.texture_reader(tiny_scenes),
    )
    results_dir = tmp_path / "results"
    model = [1.0 if index % 2 == 0 else 3.0 for index in range(len(test))]
    result_files.write_result(
        results_dir,
        f"train/{analyses.MAIN_RUN}",
        {"abs_inv_per_example": model, "config": {"flow_source": "estimated"}},
    )
    result_files.write_result(
        results_dir,
        "classical/tiny",
        {"methods": {"sfm_flow": {"abs_inv_per_example": [2.0] * len(test)}}},
    )
    runner = SimpleNamespace(
        scale=SCALE,
        results_dir=results_dir,
        print=print,
        data=lambda dataset: data,
        compared_run=lambda name: name,
    )
    result = result_files.as_stored(analyses.regimes(runner))
    examples = [contract.decode_example(test[index]) for index in range(len(test))]
    return result, examples


def test_each_pair_carries_its_own_scores_and_properties(compared):
    result, examples = compared
    rows = {row["id"]: row for row in result["rows"]}
    assert len(rows) == len(examples) == 16
    for index, example in enumerate(examples):
        row = rows[example["id"]]
        assert row["model_abs_inv"] == (1.0 if index % 2 == 0 else 3.0)
        assert row["ratio"] == (0.5 if index % 2 == 0 else 1.5)
        assert row["baseline"] == pytest.approx(np.linalg.norm(example["translation"]))
        assert row["texture_kind"] in ("plain", "checker", "stripes", "gradient", "noise")
    overall = next(row for row in result["tables"]["baseline"] if row["label"] == "all")
    assert (overall["label"], overall["pairs"], overall["model_wins"]) == ("all", 16, 0.5)
    assert set(result["tables"]) == {
        "baseline",
        "rotation_share",
        "flow_epe_px",
        "sfm_rotation_error_deg",
        "sfm_translation_error_deg",
        "texture_kind",
    }


def test_the_report_shows_its_table_and_figure(compared, tmp_path):
    result, _ = compared
    results = suite_results({analyses.MAIN_RUN: 0.03}, scale=SCALE) | {
        "regimes": {**result, "task": "regimes"}
    }
    path = paper_report.write_report(SCALE, results, tmp_path / "results", tmp_path / "report")
    readme = path.read_text()
    section = readme[readme.index("## 12.") : readme.index("## Runs and budgets")]
    assert "| all pairs |  | all | 16 | 2.0000 | 2.0000 | 1.00× | 50% |" in section
    assert "| texture kind |" in section and "![the per-pair ratio" in section
    assert (tmp_path / "report" / "regimes.png").stat().st_size > 5000
    # Without the result, the section says so.
    readme = paper_report.write_report(
        SCALE,
        suite_results({analyses.MAIN_RUN: 0.03}, scale=SCALE),
        tmp_path / "results",
        tmp_path / "other",
    ).read_text()
    assert "## 12. Where learning wins" in readme and "The comparison: not run yet." in readme
