import baseline_checks
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from global_local_reference import inv_depth_of

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


def test_each_scale_is_its_prediction_layer_and_the_output_is_pr1_upsampled():
    model = DispNet(**NARROW)
    image1, image2, flow, _, _ = baseline_checks.tiny_batch(2, 32, 32)
    variables = baseline_checks.drawn_variables(model, 32, 32)
    apply = baseline_checks.capturing(model)
    outputs, layers = apply(variables, image1, image2, flow)
    # pr1 (1/2 resolution) up-sampled bilinearly is the depth; pr2 ... pr6 the pyramid.
    full = baseline_checks.upsample_bilinear(layers["pr1"][..., 0], 32, 32)
    np.testing.assert_allclose(outputs["inv_depth"], inv_depth_of(full), rtol=1e-5, atol=1e-6)
    assert len(outputs["inv_depth_pyramid"]) == 5
    for level, scale in enumerate(outputs["inv_depth_pyramid"], start=2):
        np.testing.assert_allclose(
            scale, inv_depth_of(layers[f"pr{level}"][..., 0]), rtol=1e-5, atol=1e-6
        )
    # The pairs of a batch are predicted independently.
    changed, _ = apply(variables, image1, image2, flow + 5.0 * np.arange(2)[:, None, None, None])
    np.testing.assert_array_equal(changed["inv_depth"][0], outputs["inv_depth"][0])
    assert np.abs(changed["inv_depth"][1] - outputs["inv_depth"][1]).max() > 1e-4


@pytest.mark.slow
def test_training_learns_depth_from_the_flow():
    losses, outputs, inv_depth, _ = baseline_checks.train_tiny(DispNet(**NARROW), steps=250)
    baseline_checks.check_learned(losses, outputs, inv_depth)
    assert len(outputs["inv_depth_pyramid"]) == 5
