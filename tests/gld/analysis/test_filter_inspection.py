"""Filter-bank inspection of a trained model (gld/analysis/filter_inspection.py)."""

import numpy as np
import pytest

from gld.analysis import filter_inspection as inspect_lib
from gld.runs import workdir


def test_filter_inspection(trained_workdir, eval_batch, tmp_path):
    model, variables, _ = workdir.load_trained(trained_workdir)
    inspected = inspect_lib.filter_banks(variables, eval_batch, model=model)
    outputs = model.apply(variables, eval_batch["image1"], eval_batch["image2"], eval_batch["flow"])
    np.testing.assert_allclose(inspected["global_params"], outputs["global_params"], rtol=1e-6)
    assert [k.shape for k in inspected["kernels"]] == [
        (4, 3, 3, 4, 20),
        (4, 3, 3, 20, 10),
        (4, 3, 3, 10, 20),
    ]
    for kernel, bias, bank in zip(
        inspected["kernels"], inspected["biases"], outputs["filter_banks"], strict=True
    ):
        np.testing.assert_allclose(kernel, bank.kernel, rtol=1e-6)
        np.testing.assert_allclose(bias, bank.bias, rtol=1e-6)
    similarity = inspect_lib.filter_similarity(inspected["kernels"], inspected["biases"])
    np.testing.assert_allclose(np.diag(similarity), 1.0, rtol=1e-5)
    np.testing.assert_allclose(similarity, similarity.T, atol=1e-6)
    path = inspect_lib.draw_filter_banks(inspected["kernels"], 0, tmp_path / "f.png")
    assert path.stat().st_size > 1000


def test_motion_similarity_and_correlation_by_construction():
    rotation = np.stack([np.eye(3)] * 4)
    translation = np.array([[1.0, 0, 0], [2.0, 0, 0], [0, 1.0, 0], [0, 0, 1.0]])
    similarity = inspect_lib.motion_similarity(rotation, translation)
    # pairs 0 and 1 move in the same direction (scale differs), 0 and 2 do not
    assert similarity[0, 1] == pytest.approx(1.0)
    assert similarity[0, 2] < 0.5
    upper = np.triu(np.arange(16.0).reshape(4, 4), 1)
    matrix = upper + upper.T
    assert inspect_lib.similarity_correlation(matrix, 2 * matrix)["pearson"] == pytest.approx(1.0)
    assert inspect_lib.similarity_correlation(matrix, -matrix)["spearman"] == pytest.approx(-1.0)
