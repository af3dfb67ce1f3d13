"""The hypernetwork LP (gld/models/hypernet.py): output layout, initial modulation, gradients to g,
and the static banks of the no-global-module ablation."""

import jax
import jax.numpy as jnp
import numpy as np

from gld.models import filter_banks, hypernet


def _key(seed):
    # The 'rbg' generator compiles several times faster than threefry on CPU.
    return jax.random.key(seed, impl="rbg")


def test_output_size_matches_paper_defaults():
    assert hypernet.hypernet_output_size() == 4370
    # 5x5 kernels, two banks: 25*2*3 + 3 + 25*3*1 + 1.
    assert hypernet.hypernet_output_size(2, (3, 1), 5) == 25 * 6 + 3 + 25 * 3 + 1


def test_hypernetwork_shapes_and_initial_modulation():
    module = hypernet.HyperNetwork()
    global_params = np.random.default_rng(0).normal(size=(256, 6)).astype(np.float32)
    params = jax.jit(module.init)(_key(1), global_params)
    banks = jax.jit(module.apply)(params, global_params)
    assert [bank.kernel.shape for bank in banks] == [
        (256, 3, 3, 4, 20),
        (256, 3, 3, 20, 10),
        (256, 3, 3, 10, 20),
    ]
    assert [bank.bias.shape for bank in banks] == [(256, 20), (256, 10), (256, 20)]
    assert params["params"]["linear"]["kernel"].shape == (6, 4370)
    # Zero global parameters give the static conv stack stored in the bias: He-normal
    # kernels (std sqrt(2 / (1 + 0.2^2) / fan_in)) and zero biases.
    static = jax.jit(module.apply)(params, jnp.zeros((1, 6)))
    for bank, fan_in in zip(static, (36, 180, 90), strict=True):
        he_std = np.sqrt(2 / 1.04 / fan_in)
        assert abs(float(bank.kernel.std()) - he_std) < 0.15 * he_std
        np.testing.assert_array_equal(bank.bias, 0.0)
    # Unit-variance global parameters move each filter by ~MODULATION_SCALE of its scale.
    for bank, static_bank in zip(banks, static, strict=True):
        relative = (bank.kernel - static_bank.kernel).std() / static_bank.kernel.std()
        assert 0.5 * hypernet.MODULATION_SCALE < relative < 1.5 * hypernet.MODULATION_SCALE


def test_the_banks_are_one_linear_map_of_the_global_params_read_bank_by_bank():
    # Two banks of 3x3 filters, 2 -> 3 -> 2 channels: 54 + 3 + 54 + 2 = 113 outputs,
    # each bank's kernel (row, column, input, output; the last fastest) then its bias.
    module = hypernet.HyperNetwork(in_channels=2, bank_channels=(3, 2))
    rng = np.random.default_rng(0)
    weights = {
        "kernel": rng.normal(size=(6, 113)).astype(np.float32),
        "bias": rng.normal(size=113).astype(np.float32),
    }
    global_params = rng.normal(size=(4, 6)).astype(np.float32)
    banks = jax.jit(module.apply)({"params": {"linear": weights}}, global_params)
    flat = global_params.astype(np.float64) @ weights["kernel"] + weights["bias"]
    expected = [
        (flat[:, :54].reshape(4, 3, 3, 2, 3), flat[:, 54:57]),
        (flat[:, 57:111].reshape(4, 3, 3, 3, 2), flat[:, 111:]),
    ]
    assert len(banks) == 2
    for bank, (kernel, bias) in zip(banks, expected, strict=True):
        np.testing.assert_allclose(bank.kernel, kernel, rtol=1e-5, atol=1e-5)
        np.testing.assert_allclose(bank.bias, bias, rtol=1e-5, atol=1e-5)
    # One entry by hand: bank 1, row 2, column 0, input 1, output 0 of example 3.
    index = 57 + ((2 * 3 + 0) * 3 + 1) * 2 + 0
    np.testing.assert_allclose(
        banks[1].kernel[3, 2, 0, 1, 0],
        sum(global_params[3, g] * weights["kernel"][g, index] for g in range(6))
        + weights["bias"][index],
        rtol=1e-5,
    )


def test_hypernetwork_gradients_reach_global_params():
    module = hypernet.HyperNetwork(in_channels=2, bank_channels=(3, 2))
    rng = np.random.default_rng(0)
    global_params = rng.normal(size=(2, 6)).astype(np.float32)
    params = jax.jit(module.init)(_key(1), global_params)
    inputs = rng.normal(size=(2, 5, 5, 2)).astype(np.float32)

    def loss(global_params):
        banks = module.apply(params, global_params)
        return filter_banks.apply_filter_banks(banks, inputs).sum()

    grad = jax.jit(jax.grad(loss))(global_params)
    assert grad.shape == (2, 6) and np.all(np.abs(grad) > 0)


def test_static_filter_banks_are_shared_by_the_batch():
    module = hypernet.StaticFilterBanks(bank_channels=(3, 2), kernel_size=5)
    params = module.init(_key(0), 4)
    banks = module.apply(params, 4)
    assert banks[0].kernel.shape == (4, 5, 5, 4, 3) and banks[1].bias.shape == (4, 2)
    np.testing.assert_array_equal(banks[0].kernel[0], banks[0].kernel[3])
    np.testing.assert_array_equal(banks[0].kernel[0], params["params"]["kernel_0"])
