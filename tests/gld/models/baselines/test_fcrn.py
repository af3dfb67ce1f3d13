import baseline_checks
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from gld.models import baselines
from gld.models.baselines.fcrn import FCRN, unpool

NARROW = dict(
    stage_sizes=(1, 1, 1, 1), stem_features=8, bridge_features=32, up_features=(16, 8, 8, 8)
)


def test_unpool_places_values_top_left_of_zero_blocks():
    features = jnp.arange(2 * 3 * 2, dtype=jnp.float32).reshape(1, 2, 3, 2)
    unpooled = np.asarray(unpool(features))
    assert unpooled.shape == (1, 4, 6, 2)
    np.testing.assert_array_equal(unpooled[:, ::2, ::2], features)
    assert np.count_nonzero(unpooled[:, 1::2]) == 0
    assert np.count_nonzero(unpooled[:, :, 1::2]) == 0


def test_resnet50_shapes_and_parameter_count():
    model = FCRN()
    baseline_checks.output_shapes(model, 192, 256)
    baseline_checks.output_shapes(model, 20, 28)
    image = jax.ShapeDtypeStruct((1, 64, 64, 3), jnp.float32)
    flow = jax.ShapeDtypeStruct((1, 64, 64, 2), jnp.float32)
    variables = jax.eval_shape(model.init, jax.random.key(0), image, image, flow)
    params = variables["params"]
    assert sum(name.startswith("stage") for name in params) == 3 + 4 + 6 + 3
    assert params["stage4_block3"]["Conv_2"]["kernel"].shape == (1, 1, 512, 2048)
    assert params["bridge"]["kernel"].shape == (1, 1, 2048, 1024)
    assert "batch_stats" in variables
    # Laina et al. report 63.6M parameters; the 8-channel stem adds 5 x 7 x 7 x 64.
    assert 63.0e6 < baselines.parameter_count(model) < 64.0e6
    assert baselines.LEARNED["fcrn"] is FCRN


@pytest.mark.slow
def test_training_lowers_sparse_loss_and_updates_batch_statistics():
    losses, outputs, variables = baseline_checks.train_tiny(FCRN(**NARROW))
    baseline_checks.check_trained_outputs(losses, outputs)
    # Running statistics start at mean 0, variance 1 and move towards the batch's.
    stem_stats = variables["batch_stats"]["stem_norm"]
    assert np.max(np.abs(stem_stats["mean"])) > 1e-3
    assert np.max(np.abs(stem_stats["var"] - 1.0)) > 1e-3
