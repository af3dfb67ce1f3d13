"""The paper's numbers: one table of the paper per entry, each number read with its table."""

import pytest

from gld.paper import numbers as paper_numbers


@pytest.mark.parametrize("key", sorted(paper_numbers.TABLES))
def test_each_row_has_a_number_for_each_column_as_the_paper_prints_it(key):
    table = paper_numbers.TABLES[key]
    assert table.label.split(":")[1] == key
    assert table.model is None or table.model in table.rows
    for row in table.rows.values():
        assert len(row.printed) == len(table.columns), row.name
        assert all(float(number) > 0 for number in row.printed)


def test_the_papers_model_differs_between_its_tables():
    values = paper_numbers.model_values()
    assert values == {
        "results_sparse": 0.031,
        "gt_density": 0.031,
        "sfm_sota": 0.033,
        "ablation_studies": 0.033,
        "given_pose": 0.033,
        "finetune_flow": 0.033,
    }
    # The only dataset mean of the paper sits in its SfM table, beside its model's 0.033.
    assert paper_numbers.mean_value() == 0.069
    assert paper_numbers.x_mean("results_sparse", "global_local_1px") == pytest.approx(0.449, 1e-3)
    assert paper_numbers.x_mean("sfm_sota", "global_local_1px") == pytest.approx(0.478, 1e-3)


def test_a_number_is_read_by_table_row_and_column():
    assert paper_numbers.value("gt_density", "dispnet", "dense") == 0.023
    assert paper_numbers.value("ablation_studies", "global_local_1px", "abs_rel") == 0.45
    assert paper_numbers.printed("sfm_sota", "dataset_mean") == ("0.069", "0.771", "0.940")
    assert paper_numbers.value("results_sparse", "dataset_mean") is None
    assert paper_numbers.x_mean("results_change_intrs", "small_encdec") is None
