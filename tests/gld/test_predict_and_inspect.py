import numpy as np
import pytest
from conftest import tiny_train_config

from gld import input_pipeline, train
from gld import inspect as inspect_lib
from gld.predict import DepthPredictor


@pytest.fixture(scope="module")
def trained_workdir(tiny_scenes, tmp_path_factory):
    workdir = tmp_path_factory.mktemp("trained")
    config = tiny_train_config(steps=2, log_every=1)
    train.train_and_evaluate(
        config,
        workdir,
        tiny_scenes.as_data_source("train"),
        progress=False,
        print_fn=lambda _: None,
    )
    return workdir


@pytest.fixture(scope="module")
def eval_batch(tiny_scenes):
    source = tiny_scenes.as_data_source("test")
    return next(input_pipeline.eval_batches([source[i] for i in range(4)], batch_size=4))


def test_predictor_accepts_any_size_and_dtype_and_returns_input_size(trained_workdir, eval_batch):
    predictor = DepthPredictor.from_workdir(trained_workdir)
    rng = np.random.default_rng(0)
    image1 = rng.integers(0, 256, (50, 70, 3), dtype=np.uint8)
    image2 = np.roll(image1, 2, axis=1)
    depth = predictor(image1, image2)
    assert depth.shape == (50, 70) and np.all(depth > 0) and np.all(np.isfinite(depth))
    # float images in [0, 1] give the same answer as the uint8 ones
    np.testing.assert_allclose(predictor(image1 / 255.0, image2 / 255.0), depth, rtol=1e-4)
    # at the model's own size, with the dataset's flow, it matches a direct model call
    images1 = eval_batch["image1"] + 0.5
    images2 = eval_batch["image2"] + 0.5
    batched = predictor.predict(images1, images2, flow=eval_batch["flow"])
    direct = predictor.model.apply(
        predictor.variables, eval_batch["image1"], eval_batch["image2"], eval_batch["flow"]
    )
    np.testing.assert_allclose(batched["depth"], np.asarray(direct["depth"]), rtol=1e-4)
    np.testing.assert_allclose(
        batched["global_params"], np.asarray(direct["global_params"]), rtol=1e-4, atol=1e-7
    )


def test_predictor_names_bad_arguments(trained_workdir):
    predictor = DepthPredictor.from_workdir(trained_workdir)
    image = np.zeros((20, 30, 3), np.uint8)
    with pytest.raises(ValueError, match="image2.*shape"):
        predictor(image, np.zeros((20, 31, 3), np.uint8))
    with pytest.raises(ValueError, match="image1 must be"):
        predictor(np.zeros((20, 30), np.uint8), image)
    with pytest.raises(ValueError, match="flow must be"):
        predictor(image, image, flow=np.zeros((20, 30, 3), np.float32))
    with pytest.raises(ValueError, match=r"\[0, 1\]"):
        predictor(image.astype(np.float32) + 7.0, image.astype(np.float32))
    with pytest.raises(FileNotFoundError, match="config.json"):
        DepthPredictor.from_workdir(trained_workdir / "nowhere")


def test_filter_inspection(trained_workdir, eval_batch, tmp_path):
    model, variables, _ = train.load_trained(trained_workdir)
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
