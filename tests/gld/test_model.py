import jax
import jax.numpy as jnp
import numpy as np
import pytest

from gld import hypernet, losses
from gld import model as model_lib


def _inputs(batch=2, height=24, width=32, seed=0):
    rng = np.random.default_rng(seed)
    return (
        jnp.asarray(rng.uniform(-0.5, 0.5, (batch, height, width, 3)), jnp.float32),
        jnp.asarray(rng.uniform(-0.5, 0.5, (batch, height, width, 3)), jnp.float32),
        jnp.asarray(rng.normal(size=(batch, height, width, 2)) * 3, jnp.float32),
    )


def test_paper_architecture_shapes_and_hypernetwork_size():
    model = model_lib.GlobalLocal()
    image1, image2, flow = _inputs()
    variables = model.init(jax.random.key(0), image1, image2, flow)
    outputs = model.apply(variables, image1, image2, flow)
    assert outputs["inv_depth"].shape == (2, 24, 32)
    assert bool(jnp.all(outputs["inv_depth"] > 0))
    np.testing.assert_allclose(outputs["depth"] * outputs["inv_depth"], 1.0, rtol=1e-5)
    assert outputs["global_params"].shape == (2, 6)
    shapes = [(b.kernel.shape, b.bias.shape) for b in outputs["filter_banks"]]
    assert shapes == [
        ((2, 3, 3, 4, 20), (2, 20)),
        ((2, 3, 3, 20, 10), (2, 10)),
        ((2, 3, 3, 10, 20), (2, 20)),
    ]
    assert hypernet.hypernet_output_size() == 4370
    counts = model_lib.parameter_counts(variables["params"])
    assert counts["hypernet"] == 6 * 4370 + 4370
    assert counts["final_conv"] == 3 * 3 * 20 + 1


def test_different_pairs_get_different_filters():
    model = model_lib.GlobalLocal()
    image1, image2, flow = _inputs()
    variables = model.init(jax.random.key(0), image1, image2, flow)
    banks = model.apply(variables, image1, image2, flow)["filter_banks"]
    assert not np.allclose(banks[0].kernel[0], banks[0].kernel[1])


@pytest.mark.parametrize(
    "ablation, local_channels",
    [
        ({"use_image_pair": False}, 4),
        ({"use_coordinates": False}, 2),
        ({"use_global_module": False}, 4),
        ({"use_flow": False}, 8),
    ],
)
def test_ablations_change_what_the_model_sees(ablation, local_channels):
    model = model_lib.GlobalLocal(**ablation)
    image1, image2, flow = _inputs()
    variables = model.init(jax.random.key(0), image1, image2, flow)
    outputs = model.apply(variables, image1, image2, flow)
    assert outputs["filter_banks"][0].kernel.shape[-2] == local_channels
    assert outputs["inv_depth"].shape == (2, 24, 32)
    params = variables["params"]
    if ablation.get("use_global_module") is False:
        assert "global_encoder" not in params and "static_filters" in params
        # static filters: every example gets the same bank
        np.testing.assert_array_equal(
            outputs["filter_banks"][0].kernel[0], outputs["filter_banks"][0].kernel[1]
        )
    if ablation.get("use_image_pair") is False:
        assert params["global_encoder"]["conv0"]["kernel"].shape[-2] == 2
    if ablation.get("use_flow") is False:
        # flow must not matter at all
        other = model.apply(variables, image1, image2, flow * 0 + 5.0)
        np.testing.assert_allclose(other["inv_depth"], outputs["inv_depth"], rtol=1e-6)


def test_gradients_reach_the_hypernetwork_and_the_global_encoder():
    model = model_lib.GlobalLocal()
    image1, image2, flow = _inputs()
    variables = model.init(jax.random.key(0), image1, image2, flow)
    batch = {
        "image1": image1,
        "depth": jnp.full((2, 24, 32), 3.0),
        "sparse_mask": jnp.zeros((2, 24, 32), bool).at[:, 5, 7].set(True),
    }

    def loss_fn(params):
        outputs = model.apply({"params": params}, image1, image2, flow)
        return losses.total_loss(outputs, batch)[0]

    grads = jax.grad(loss_fn)(variables["params"])
    for module in ("global_encoder", "hypernet", "final_conv"):
        norm = sum(float(jnp.sum(g**2)) for g in jax.tree_util.tree_leaves(grads[module]))
        assert norm > 0, module
    first_conv = grads["global_encoder"]["conv0"]["kernel"]
    assert float(jnp.abs(first_conv).sum()) > 0


def test_bad_inputs_are_named():
    model = model_lib.GlobalLocal()
    image1, image2, flow = _inputs()
    variables = model.init(jax.random.key(0), image1, image2, flow)
    with pytest.raises(ValueError, match="flow"):
        model.apply(variables, image1, image2, flow[..., :1])
    with pytest.raises(ValueError, match="image2"):
        model.apply(variables, image1, image2[:, :10], flow)
    with pytest.raises(ValueError, match="unknown model"):
        model_lib.make_model("resnet9000")


def test_local_flow_units_scale_only_the_local_input():
    image1, image2, flow = _inputs()
    normalised = model_lib.GlobalLocal()
    pixels = model_lib.GlobalLocal(local_flow_units="pixels")
    variables = normalised.init(jax.random.key(0), image1, image2, flow)
    # same parameters; the pixel model sees flow * [W, H] where the other sees flow
    scaled = flow / jnp.asarray([32.0, 24.0])
    a = pixels.apply(variables, image1, image2, flow)
    b = normalised.apply(variables, image1, image2, flow)
    assert not np.allclose(a["inv_depth"], b["inv_depth"])
    np.testing.assert_allclose(a["global_params"], b["global_params"], rtol=1e-6)
    with pytest.raises(ValueError, match="local_flow_units"):
        model_lib.GlobalLocal(local_flow_units="metres").init(
            jax.random.key(0), image1, image2, scaled
        )
