import baseline_checks
import jax
import jax.numpy as jnp
import pytest

from gld.models import baselines
from gld.models.baselines.dispnet import DispNet

NARROW = dict(encoder_features=(8, 8, 16, 16, 16, 32), decoder_features=(16, 16, 8, 8, 8))


def test_shapes_at_paper_size():
    outputs = baseline_checks.output_shapes(DispNet(), 192, 256)
    # pr2 ... pr6 at 1/4 ... 1/64 resolution, finest first.
    assert [scale.shape for scale in outputs["inv_depth_pyramid"]] == [
        (2, 48, 64),
        (2, 24, 32),
        (2, 12, 16),
        (2, 6, 8),
        (2, 3, 4),
    ]


def test_sizes_not_divisible_by_64_are_cropped_to_the_skips():
    outputs = baseline_checks.output_shapes(DispNet(), 20, 28)
    assert [scale.shape[1:] for scale in outputs["inv_depth_pyramid"]] == [
        (5, 7),
        (3, 4),
        (2, 2),
        (1, 1),
        (1, 1),
    ]


def test_original_layer_sizes():
    model = DispNet()
    image = jax.ShapeDtypeStruct((1, 64, 64, 3), jnp.float32)
    flow = jax.ShapeDtypeStruct((1, 64, 64, 2), jnp.float32)
    params = jax.eval_shape(model.init, jax.random.key(0), image, image, flow)["params"]
    assert params["conv1"]["kernel"].shape == (7, 7, 8, 64)
    assert params["conv6b"]["kernel"].shape == (3, 3, 1024, 1024)
    # iconv1 sees upconv1 (32) + the up-sampled pr2 (1) + conv1 (64).
    assert params["iconv1"]["kernel"].shape == (3, 3, 32 + 1 + 64, 32)
    assert baselines.LEARNED["dispnet"] is DispNet


@pytest.mark.slow
def test_training_lowers_sparse_loss():
    losses, outputs, _ = baseline_checks.train_tiny(DispNet(**NARROW))
    baseline_checks.check_trained_outputs(losses, outputs)
    assert len(outputs["inv_depth_pyramid"]) == 5
