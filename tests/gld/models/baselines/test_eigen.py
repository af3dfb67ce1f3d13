import baseline_checks
import jax
import jax.numpy as jnp
import pytest

from gld.models import baselines
from gld.models.baselines.eigen import EigenNet

# Same layers, narrower: compiles and trains in seconds.
NARROW = dict(coarse_features=(8, 16, 16, 16, 16), hidden_units=64, fine_features=(8, 8))


def test_shapes_at_paper_size():
    model = EigenNet()
    image = jax.ShapeDtypeStruct((2, 192, 256, 3), jnp.float32)
    flow = jax.ShapeDtypeStruct((2, 192, 256, 2), jnp.float32)
    variables = jax.eval_shape(model.init, jax.random.key(0), image, image, flow)
    # Coarse 5 output: 256x192 / 4 (stride) / 2 / 2 / 2 (pools) = 8x6 x 256 channels.
    assert variables["params"]["coarse6"]["kernel"].shape == (8 * 6 * 256, 4096)
    # The coarse output is a 1/4-resolution map, one value per output pixel.
    assert variables["params"]["coarse7"]["kernel"].shape == (4096, 48 * 64)
    outputs = jax.eval_shape(lambda v, i, f: model.apply(v, i, i, f), variables, image, flow)
    assert outputs["inv_depth"].shape == (2, 192, 256)
    assert [scale.shape for scale in outputs["inv_depth_pyramid"]] == [(2, 48, 64)]


@pytest.mark.parametrize("height, width", [(48, 64), (32, 32), (20, 28)])
def test_dense_layers_follow_the_input_size(height, width):
    outputs = baseline_checks.output_shapes(EigenNet(), height, width)
    coarse = outputs["inv_depth_pyramid"][0]
    assert coarse.shape == (2, -(-height // 4), -(-width // 4))


def test_registered_and_counted():
    assert baselines.LEARNED["eigen"] is EigenNet
    narrow = baselines.parameter_count(EigenNet(**NARROW), 32, 32)
    # The dense layers grow with the input: 2x the pixels, 2x the coarse7 outputs.
    assert baselines.parameter_count(EigenNet(**NARROW), 64, 32) > narrow + 64 * 64


def test_training_lowers_sparse_loss():
    losses, outputs, _ = baseline_checks.train_tiny(EigenNet(**NARROW))
    baseline_checks.check_trained_outputs(losses, outputs)
    assert outputs["inv_depth_pyramid"][0].shape == (2, 8, 8)
