import baseline_checks
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from global_local_reference import inv_depth_of

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


def test_the_output_is_the_prediction_upsampled_and_only_training_mixes_the_batch():
    # One stage (stride 1 after the stem's 2 and the pooling's 2), one up-projection: the
    # prediction is at 1/2 resolution, as in the full model; cheap to compile.
    model = FCRN(stage_sizes=(1,), stem_features=4, bridge_features=8, up_features=(4,))
    image1, image2, flow, _, _ = baseline_checks.tiny_batch(2, 16, 16)
    variables = baseline_checks.drawn_variables(model, 16, 16)
    apply = baseline_checks.capturing(model)
    outputs, layers = apply(variables, image1, image2, flow)
    # The prediction, up-sampled bilinearly to the input.
    assert layers["prediction"].shape == (2, 8, 8, 1)
    full = baseline_checks.upsample_bilinear(layers["prediction"][..., 0], 16, 16)
    np.testing.assert_allclose(outputs["inv_depth"], inv_depth_of(full), rtol=1e-5, atol=1e-6)
    # Evaluation normalises with the running statistics: pair 0's depth does not depend
    # on pair 1. Training normalises with the batch's statistics: it does.
    other_flow = flow.copy()
    other_flow[1] += 5.0
    changed, _ = apply(variables, image1, image2, other_flow)
    np.testing.assert_array_equal(changed["inv_depth"][0], outputs["inv_depth"][0])

    in_training = baseline_checks.capturing(model, train=True, mutable=["batch_stats"])
    first, _ = in_training(variables, image1, image2, flow)
    second, _ = in_training(variables, image1, image2, other_flow)
    assert np.abs(second["inv_depth"][0] - first["inv_depth"][0]).max() > 1e-4


@pytest.mark.slow
def test_training_learns_depth_from_the_flow_and_updates_batch_statistics():
    model = FCRN(**NARROW)
    losses, outputs, inv_depth, variables = baseline_checks.train_tiny(
        model, steps=300, learning_rate=3e-3
    )
    baseline_checks.check_learned(losses, outputs, inv_depth)
    # Running statistics start at mean 0, variance 1 and move towards the batch's.
    stem_stats = variables["batch_stats"]["stem_norm"]
    assert np.max(np.abs(stem_stats["mean"])) > 1e-3
    assert np.max(np.abs(stem_stats["var"] - 1.0)) > 1e-3
