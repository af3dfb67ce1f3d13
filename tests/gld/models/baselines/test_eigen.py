import baseline_checks
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from global_local_reference import inv_depth_of

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


def test_the_coarse_network_sees_the_whole_image_and_the_output_is_the_fine_map_upsampled():
    model = EigenNet(**NARROW)
    image1, image2, flow, _, _ = baseline_checks.tiny_batch(2, 32, 32)
    variables = baseline_checks.drawn_variables(model, 32, 32)
    apply = baseline_checks.capturing(model)
    outputs, layers = apply(variables, image1, image2, flow)
    # The depth is the fine network's 1/4-resolution map, up-sampled bilinearly; the
    # pyramid holds the coarse network's map, one dense output per pixel of it.
    fine = baseline_checks.upsample_bilinear(layers["fine4"][..., 0], 32, 32)
    np.testing.assert_allclose(outputs["inv_depth"], inv_depth_of(fine), rtol=1e-5, atol=1e-6)
    coarse = layers["coarse7"].reshape(2, 8, 8)
    np.testing.assert_allclose(
        outputs["inv_depth_pyramid"][0], inv_depth_of(coarse), rtol=1e-5, atol=1e-6
    )
    # One input pixel in a corner of pair 0 moves the coarse map at the opposite corner
    # (the dense layers see everything), and nothing of pair 1.
    changed_flow = flow.copy()
    changed_flow[0, 0, 0] += 100.0
    changed, _ = apply(variables, image1, image2, changed_flow)
    coarse_change = np.abs(changed["inv_depth_pyramid"][0] - outputs["inv_depth_pyramid"][0])
    assert coarse_change[0, -1, -1] > 1e-5
    np.testing.assert_array_equal(changed["inv_depth"][1], outputs["inv_depth"][1])
    np.testing.assert_array_equal(coarse_change[1], 0.0)


# A baseline's learning (~17 s): an option no main recipe uses; the slow run checks it.
@pytest.mark.slow
def test_training_learns_depth_from_the_flow():
    losses, outputs, inv_depth, _ = baseline_checks.train_tiny(EigenNet(**NARROW), steps=150)
    baseline_checks.check_learned(losses, outputs, inv_depth)
    assert outputs["inv_depth_pyramid"][0].shape == (16, 8, 8)
