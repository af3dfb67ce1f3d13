"""DepthPredictor (gld/predict.py): any image size and dtype, clear errors."""

import numpy as np
import pytest

from gld.predict import DepthPredictor


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
