"""The per-example convolution engine (gld/models/filter_banks.py): every formulation equals a loop
of plain convolutions, in values and gradients, on one device and on a sharded mesh."""

import textwrap

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import run_on_cpu_devices
from jax import lax

from gld.models import filter_banks
from gld.models.convolutions import conv_single
from gld.models.filter_banks import FilterBank, SharedConv

BANK_CHANNELS = (5, 3, 4)
IN_CHANNELS = 4


def _loop_reference(filter_banks, inputs, negative_slope):
    """A Python loop of plain per-example convolutions, the ground truth."""
    outputs = []
    for index in range(inputs.shape[0]):
        activations = inputs[index : index + 1]
        for bank in filter_banks:
            activations = lax.conv_general_dilated(
                activations,
                bank.kernel[index],
                (1, 1),
                "SAME",
                dimension_numbers=("NHWC", "HWIO", "NHWC"),
                precision=lax.Precision.HIGHEST,
            )
            activations = jax.nn.leaky_relu(activations + bank.bias[index], negative_slope)
        outputs.append(activations[0])
    return jnp.stack(outputs)


def _random_banks(seed, batch_size, kernel_size=3, bank_channels=BANK_CHANNELS):
    rng = np.random.default_rng(seed)
    banks = []
    channels = [IN_CHANNELS, *bank_channels]
    for c_in, c_out in zip(channels[:-1], channels[1:], strict=True):
        shape = (batch_size, kernel_size, kernel_size, c_in, c_out)
        kernel = rng.normal(size=shape) / np.sqrt(kernel_size * kernel_size * c_in)
        bias = 0.3 * rng.normal(size=(batch_size, c_out))
        banks.append(FilterBank(jnp.asarray(kernel, jnp.float32), jnp.asarray(bias, jnp.float32)))
    return banks


def _random_head(seed, kernel_size=3, c_out=2):
    """A conv shared by the batch after the last bank (the model's final conv)."""
    rng = np.random.default_rng(seed)
    shape = (kernel_size, kernel_size, BANK_CHANNELS[-1], c_out)
    kernel = rng.normal(size=shape) / np.sqrt(kernel_size * kernel_size * BANK_CHANNELS[-1])
    return SharedConv(
        jnp.asarray(kernel, jnp.float32), jnp.asarray(rng.normal(size=c_out), jnp.float32)
    )


def _head_reference(outputs, head):
    conv = lax.conv_general_dilated(
        outputs,
        head.kernel,
        (1, 1),
        "SAME",
        dimension_numbers=("NHWC", "HWIO", "NHWC"),
        precision=lax.Precision.HIGHEST,
    )
    return conv + head.bias


def _loss_fn(formulation_fn, channels=BANK_CHANNELS[-1]):
    # A fixed random projection makes every output element matter to the gradient.
    weights = np.random.default_rng(7).normal(size=(3, 6, 7, channels)).astype(np.float32)

    def loss(banks, inputs):
        return jnp.sum(formulation_fn(banks, inputs) * weights)

    return loss


SLOPE = 0.2


@pytest.fixture(scope="module", params=["banks", "banks_and_head"])
def reference_case(request):
    """Inputs, layers (banks, and a head or None), and the loop reference's outputs and
    gradients (computed once per case)."""
    inputs = jnp.asarray(np.random.default_rng(0).normal(size=(3, 6, 7, IN_CHANNELS)), jnp.float32)
    layers = (_random_banks(1, 3), _random_head(2) if request.param == "banks_and_head" else None)

    def reference(layers, inputs):
        banks, head = layers
        outputs = _loop_reference(banks, inputs, SLOPE)
        return outputs if head is None else _head_reference(outputs, head)

    channels = BANK_CHANNELS[-1] if layers[1] is None else layers[1].kernel.shape[-1]
    outputs = jax.jit(reference)(layers, inputs)
    grads = jax.jit(jax.grad(_loss_fn(reference, channels), argnums=(0, 1)))(layers, inputs)
    return inputs, layers, outputs, grads, channels


def _assert_bank_grads_equal(got, want):
    got_banks, got_head = got
    want_banks, want_head = want
    for got_bank, want_bank in zip(got_banks, want_banks, strict=True):
        np.testing.assert_allclose(got_bank.kernel, want_bank.kernel, rtol=1e-4, atol=1e-4)
        np.testing.assert_allclose(got_bank.bias, want_bank.bias, rtol=1e-4, atol=1e-4)
    assert (got_head is None) == (want_head is None)
    if want_head is not None:
        np.testing.assert_allclose(got_head.kernel, want_head.kernel, rtol=1e-4, atol=1e-4)
        np.testing.assert_allclose(got_head.bias, want_head.bias, rtol=1e-4, atol=1e-4)


@pytest.mark.parametrize("formulation", sorted(filter_banks.FORMULATIONS))
def test_formulation_matches_loop_of_plain_convs(formulation, reference_case):
    # At float32's full precision: on a GPU, JAX's default is TF32, whose rounding (up to
    # 1e-3 relative on an H200) the matmul formulations would show against the reference.
    with jax.default_matmul_precision("highest"):
        _check_formulation_matches_loop_of_plain_convs(formulation, reference_case)


def _check_formulation_matches_loop_of_plain_convs(formulation, reference_case):
    inputs, layers, expected_outputs, expected_grads, channels = reference_case

    def apply(layers, inputs):
        banks, head = layers
        return filter_banks.apply_filter_banks(
            banks, inputs, head=head, formulation=formulation, negative_slope=SLOPE
        )

    np.testing.assert_allclose(
        jax.jit(apply)(layers, inputs), expected_outputs, rtol=1e-4, atol=1e-5
    )
    loss = _loss_fn(apply, channels)
    layer_grads, input_grads = jax.jit(jax.grad(loss, argnums=(0, 1)))(layers, inputs)
    _assert_bank_grads_equal(layer_grads, expected_grads[0])
    np.testing.assert_allclose(input_grads, expected_grads[1], rtol=1e-4, atol=1e-4)
    # Inputs that are data (as in the model): only the layers are differentiated.
    _assert_bank_grads_equal(jax.jit(jax.grad(loss))(layers, inputs), expected_grads[0])


@pytest.mark.parametrize("c_in, c_out", [(3, 17), (18, 20), (20, 5), (33, 2), (17, 1)])
def test_sliced_kernel_gradient_matches_autodiff_across_slices(c_in, c_out):
    # The CPU default's kernel gradient cuts channel counts above 16 into slices of 16
    # (both sides, with a short last slice); a head's one output channel stays whole.
    rng = np.random.default_rng(100 * c_in + c_out)
    image = jnp.asarray(rng.normal(size=(6, 7, c_in)), jnp.float32)
    cotangent = jnp.asarray(rng.normal(size=(6, 7, c_out)), jnp.float32)
    kernel = jnp.zeros((3, 3, c_in, c_out), jnp.float32)
    with jax.default_matmul_precision("highest"):
        _, vjp = jax.vjp(lambda k: conv_single(image, k), kernel)
        (expected,) = vjp(cotangent)
        got = jax.jit(filter_banks._kernel_grad_sliced)(image, cotangent, kernel)
    np.testing.assert_allclose(got, expected, rtol=1e-4, atol=1e-4)


def test_default_formulation_is_the_measured_choice_per_platform():
    # CPU: the fused custom-VJP stack with channels aligned to the vectors (fastest on the
    # 2-core benchmark); GPU and any other platform: "vmap", one grouped convolution.
    expected = {
        "cpu": "fused_aligned",
        "gpu": "vmap",
        "cuda": "vmap",
        "rocm": "vmap",
        "tpu": "vmap",
    }
    for backend, name in expected.items():
        assert filter_banks.default_formulation(backend) == name, backend
        assert name in filter_banks.FORMULATIONS
    assert filter_banks.default_formulation() == expected[jax.default_backend()]


@pytest.mark.parametrize(
    "change, message",
    [
        (lambda banks, x: (banks, x[0]), "inputs must be"),
        (lambda banks, x: (banks, x[..., :3]), "input channels"),
        (lambda banks, x: (banks[1:], x), "input channels"),
        (lambda banks, x: ([FilterBank(banks[0].kernel, banks[0].bias[:, :2])], x), "bias"),
        (lambda banks, x: ([FilterBank(banks[0].kernel[:, :2, :2], banks[0].bias)], x), "odd"),
    ],
)
def test_apply_filter_banks_rejects_bad_shapes(change, message):
    banks = _random_banks(0, 2)
    inputs = jnp.zeros((2, 6, 7, IN_CHANNELS))
    bad_banks, bad_inputs = change(banks, inputs)
    with pytest.raises(ValueError, match=message):
        filter_banks.apply_filter_banks(bad_banks, bad_inputs)
    with pytest.raises(ValueError, match="unknown formulation"):
        filter_banks.apply_filter_banks(banks, inputs, formulation="nope")


@pytest.mark.parametrize(
    "head, message",
    [
        (SharedConv(jnp.zeros((2, 3, 3, BANK_CHANNELS[-1], 1)), jnp.zeros(1)), "head.kernel must"),
        (SharedConv(jnp.zeros((3, 3, BANK_CHANNELS[-1] + 1, 1)), jnp.zeros(1)), "last bank"),
        (SharedConv(jnp.zeros((3, 3, BANK_CHANNELS[-1], 1)), jnp.zeros(2)), "head.bias"),
    ],
)
def test_apply_filter_banks_rejects_bad_head(head, message):
    inputs = jnp.zeros((2, 6, 7, IN_CHANNELS))
    with pytest.raises(ValueError, match=message):
        filter_banks.apply_filter_banks(_random_banks(0, 2), inputs, head=head)


SHARDED_SCRIPT = textwrap.dedent(
    """
    import json
    import jax, jax.numpy as jnp, numpy as np
    from jax.sharding import NamedSharding, PartitionSpec
    from gld.models import filter_banks
    from gld.models.filter_banks import FilterBank, SharedConv
    from gld.sharding import BATCH_AXIS

    assert len(jax.devices()) == 2
    axis_types = jax.sharding.AxisType
    rng = np.random.default_rng(0)
    as_f32 = lambda *shape: jnp.asarray(rng.normal(size=shape), jnp.float32)
    inputs = as_f32(4, 6, 7, 3)
    banks = [FilterBank(as_f32(4, 3, 3, 3, 5), as_f32(4, 5)),
             FilterBank(as_f32(4, 3, 3, 5, 2), as_f32(4, 2))]
    head = SharedConv(as_f32(3, 3, 2, 1), as_f32(1))
    weights = as_f32(4, 6, 7, 1)
    result = {}
    for formulation in ("fused", "map_conv", "vmap"):
        def loss(layers, inputs):
            banks, head = layers
            outputs = filter_banks.apply_filter_banks(
                banks, inputs, head=head, formulation=formulation)
            return jnp.sum(outputs * weights)
        grad = jax.jit(jax.grad(loss))
        single = grad((banks, head), inputs)
        for axis_type in (axis_types.Auto, axis_types.Explicit):
            mesh = jax.make_mesh((2,), (BATCH_AXIS,), axis_types=(axis_type,))
            sharding = NamedSharding(mesh, PartitionSpec(BATCH_AXIS))
            with jax.set_mesh(mesh):
                sharded = grad((banks, head), jax.device_put(inputs, sharding))
            result[f"{formulation}/{axis_type}"] = max(
                float(jnp.max(jnp.abs(a - b)) / jnp.max(jnp.abs(a)))
                for a, b in zip(jax.tree.leaves(single), jax.tree.leaves(sharded)))
    print(json.dumps(result))
    """
)


@pytest.mark.slow
def test_banks_on_a_batch_sharded_mesh_give_the_single_device_gradients():
    # Under a mesh the banks run on each device's shard of the batch (shard_map); the
    # shared head's gradient must still sum over all examples of all devices.
    relative_errors = run_on_cpu_devices(SHARDED_SCRIPT, 2)
    for formulation, error in relative_errors.items():
        assert error < 1e-5, (formulation, error)
