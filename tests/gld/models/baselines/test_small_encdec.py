import baseline_checks
import jax
import numpy as np
import pytest
from global_local_reference import conv_same, inv_depth_of, leaky_relu

from gld.models import baselines
from gld.models.baselines.small_encdec import SmallEncDec


def test_parameter_count_matches_the_papers_layers():
    # Encoder 8->16 (7x7), 16->32 (5x5), 32->54, 54->128 (3x3); decoder 3x3 convs
    # 128->128, (128+54)->64, (64+32)->32, (32+16)->16; prediction (16+8)->1, with biases.
    expected = (
        (7 * 7 * 8 * 16 + 16)
        + (5 * 5 * 16 * 32 + 32)
        + (9 * 32 * 54 + 54)
        + (9 * 54 * 128 + 128)
        + (9 * 128 * 128 + 128)
        + (9 * 182 * 64 + 64)
        + (9 * 96 * 32 + 32)
        + (9 * 48 * 16 + 16)
        + (9 * 24 + 1)
    )
    assert baselines.parameter_count(SmallEncDec(), 192, 256) == expected
    assert baselines.LEARNED["small_encdec"] is SmallEncDec


def test_shapes_at_paper_size_and_odd_tiny_size():
    outputs = baseline_checks.output_shapes(SmallEncDec(), 192, 256)
    assert "inv_depth_pyramid" not in outputs
    # 20x28 halves to 10x14, 5x7, 3x4, 2x2: up-sampling overshoots and must be cropped.
    baseline_checks.output_shapes(SmallEncDec(), 20, 28)


def _small_encdec_by_hand(params, image1, image2, flow):
    """The documented network in numpy: stride-2 encoder; per decoder layer x2
    nearest-neighbour up-sampling cropped to the skip, a conv, LeakyReLU, the skip
    appended (the input itself last); a 3x3 prediction."""
    _, height, width, _ = flow.shape
    features = np.concatenate([image1, image2, flow / [width, height]], axis=-1)
    skips = [features]
    for index in (1, 2):
        layer = params[f"encoder{index}"]
        features = leaky_relu(conv_same(features, layer["kernel"], layer["bias"], stride=2))
        skips.append(features)
    skips.pop()  # the bottleneck
    for index in (1, 2):
        skip = skips.pop()
        features = features.repeat(2, axis=1).repeat(2, axis=2)
        features = features[:, : skip.shape[1], : skip.shape[2]]
        layer = params[f"decoder{index}"]
        features = leaky_relu(conv_same(features, layer["kernel"], layer["bias"]))
        features = np.concatenate([features, skip], axis=-1)
    layer = params["prediction"]
    return inv_depth_of(conv_same(features, layer["kernel"], layer["bias"])[..., 0])


def test_the_network_is_the_documented_encoder_decoder():
    # Two levels, odd sizes: 5x7 halves to 3x4, then 2x2; the decoder crops back up.
    model = SmallEncDec(encoder_features=(3, 4), encoder_kernels=(5, 3), decoder_features=(4, 3))
    image1, image2, flow, _, _ = baseline_checks.tiny_batch(2, 5, 7)
    variables = baseline_checks.drawn_variables(model, 5, 7)
    outputs = jax.jit(model.apply)(variables, image1, image2, flow)
    expected = _small_encdec_by_hand(variables["params"], image1, image2, flow)
    np.testing.assert_allclose(outputs["inv_depth"], expected, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(outputs["depth"], 1.0 / expected, rtol=1e-5)


# A baseline's learning (~17 s): an option no main recipe uses; the slow run checks it.
@pytest.mark.slow
def test_training_learns_depth_from_the_flow():
    losses, outputs, inv_depth, _ = baseline_checks.train_tiny(SmallEncDec(), steps=100)
    baseline_checks.check_learned(losses, outputs, inv_depth)
