"""Per-example convolutions: the engine that runs the filter banks a hypernetwork makes.

Every example of a batch is convolved with its own filters (`FilterBank`, batched), and
the local network ends with a conv shared by the batch (`SharedConv`, the head).
`apply_filter_banks` applies such banks. The design's reference is a `jax.vmap` over
`lax.conv_general_dilated` ("vmap"), which XLA lowers to a grouped convolution that is
very slow to differentiate on CPU; the other entries of `FORMULATIONS` compute the same
function (outputs and gradients) in forms that XLA compiles to better code, five of
them with a hand-written backward pass. `default_formulation()` picks the formulation
measured fastest on each platform (`python -m experiments.benchmark`): "fused_aligned"
on CPU, "vmap" on GPU. On a mesh, each device applies the banks of its own share of the
batch (`gld.sharding.on_batch_shards`). The formulations are built from the pieces of
`gld.models.convolutions`.
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Sequence
from typing import NamedTuple

import jax
import jax.numpy as jnp
from jax import lax

from gld.models import layers
from gld.models.convolutions import (
    XLA_CONV_CHANNELS,
    aligned_conv_single,
    conv,
    conv_single,
    conv_valid,
    im2col_conv_single,
    im2col_patches,
    input_grad_conv,
    leaky_relu_grad,
    shifted_conv,
    shifted_views,
)
from gld.sharding import on_batch_shards


class FilterBank(NamedTuple):
    """One per-example convolution layer.

    Attributes:
      kernel: [B, k, k, C_in, C_out] filters of each example (HWIO per example).
      bias: [B, C_out] biases of each example.
    """

    kernel: jax.Array
    bias: jax.Array


class SharedConv(NamedTuple):
    """A convolution shared by the whole batch (the local network's final conv).

    Attributes:
      kernel: [k, k, C_in, C_out] (HWIO).
      bias: [C_out].
    """

    kernel: jax.Array
    bias: jax.Array


# ----------------------------------------------------------------------------------
# Formulations. Each takes (filter_banks, inputs [B, H, W, C_in], negative_slope, head)
# and returns [B, H, W, C_out of the last bank] ('SAME' padding, stride 1, LeakyReLU
# after every bank), or of the head when one is given: a conv shared by the batch,
# applied to the last bank's output without an activation.


def _apply_stack(
    conv: Callable[[jax.Array, jax.Array], jax.Array],
    filter_banks: Sequence[FilterBank],
    inputs: jax.Array,
    negative_slope: float,
) -> jax.Array:
    """Bank after bank: conv + bias + LeakyReLU, with `conv` batched per example."""
    activations = inputs
    for bank in filter_banks:
        pre = conv(activations, bank.kernel) + bank.bias[..., None, None, :]
        activations = jax.nn.leaky_relu(pre, negative_slope)
    return activations


def _with_head(formulation):
    """A formulation of the banks alone, followed by the head as one batched conv."""

    def with_head(filter_banks, inputs, negative_slope, head):
        outputs = formulation(filter_banks, inputs, negative_slope)
        return outputs if head is None else conv(outputs, head.kernel) + head.bias

    with_head.__doc__ = formulation.__doc__
    return with_head


@_with_head
def _vmap_formulation(filter_banks, inputs, negative_slope):
    """The design's reference: `jax.vmap` over `lax.conv_general_dilated`."""
    return _apply_stack(jax.vmap(conv_single), filter_banks, inputs, negative_slope)


def _mapped_stack(conv_single: Callable[[jax.Array, jax.Array], jax.Array]):
    """A formulation that runs the whole stack one example at a time under `lax.map`,
    with `conv_single(image [H, W, C_in], kernel [k, k, C_in, C_out])` as its conv."""

    @_with_head
    def formulation(filter_banks, inputs, negative_slope):
        def one_example(args):
            image, banks = args
            return _apply_stack(conv_single, banks, image, negative_slope)

        return lax.map(one_example, (inputs, list(filter_banks)))

    return formulation


@_with_head
def _shifted_formulation(filter_banks, inputs, negative_slope):
    """Whole batch at once, each conv a sum of k*k shifted batched matmuls."""
    return _apply_stack(shifted_conv, filter_banks, inputs, negative_slope)


# --- Custom VJP of the whole stack: per-example forward, matmul gradients. ----------
#
# XLA differentiates a per-example conv into a filter-gradient convolution at batch 1,
# which its CPU backend runs slowly. These formulations write the backward pass by
# hand: every example goes through the whole stack in one `lax.map` iteration (its
# activations stay in cache), the kernel gradient is a forward-style convolution or
# matmul over pixels, and the input gradient (skipped when the input is data) a conv.
# A backend maps one example through one bank and back; each works in its own layout.


class _StackBackend(NamedTuple):
    """Per-example pieces of a fused stack, in the backend's own activation layout."""

    # [B, H, W, C] -> [B, *layout] and back.
    to_layout: Callable[[jax.Array], jax.Array]
    from_layout: Callable[[jax.Array], jax.Array]
    # (activation, kernel [k, k, C_in, C_out], bias [C_out]) -> pre-activation.
    forward: Callable[[jax.Array, jax.Array, jax.Array], jax.Array]
    # (bank input, pre-activation cotangent, kernel) -> kernel cotangent.
    kernel_grad: Callable[[jax.Array, jax.Array, jax.Array], jax.Array]
    # (pre-activation cotangent, kernel) -> bank-input cotangent.
    input_grad: Callable[[jax.Array, jax.Array], jax.Array]
    # pre-activation cotangent -> bias cotangent.
    bias_grad: Callable[[jax.Array], jax.Array]


def _kernel_grad_taps(image: jax.Array, cotangent: jax.Array, kernel: jax.Array) -> jax.Array:
    """NHWC kernel gradient as k*k matmuls over pixels, one per tap (no patch tensor).

    image: [H, W, C_in]; cotangent: [H, W, C_out] -> [k, k, C_in, C_out].
    """
    views = shifted_views(image, kernel.shape[0])
    taps = [jnp.einsum("hwc,hwd->cd", view, cotangent) for view in views]
    return jnp.stack(taps).reshape(kernel.shape)


def _kernel_grad_im2col(image: jax.Array, cotangent: jax.Array, kernel: jax.Array) -> jax.Array:
    """NHWC kernel gradient as one matmul: patches [HW, k*k*C_in]^T @ cotangent [HW, C_out]."""
    patches = im2col_patches(image, kernel.shape[0])
    return jnp.einsum("hwp,hwd->pd", patches, cotangent).reshape(kernel.shape)


def _kernel_grad_conv(image: jax.Array, cotangent: jax.Array, kernel: jax.Array) -> jax.Array:
    """NHWC kernel gradient as one plain convolution that XLA hands to its fast conv.

    The correlation of the padded image with the cotangent is a VALID conv whose
    "batch" is the smaller of C_in and C_out and whose "kernel" is the other tensor
    (spatial size H x W); its output is the k x k filter gradient. XLA's own
    filter-gradient conv at batch 1 is much slower.

    image: [H, W, C_in]; cotangent: [H, W, C_out] -> [k, k, C_in, C_out].
    """
    pad = kernel.shape[0] // 2
    c_in, c_out = kernel.shape[2:]
    if c_in <= c_out:
        padded = jnp.pad(image, ((pad, pad), (pad, pad), (0, 0)))
        lhs = padded.transpose(2, 0, 1)[..., None]  # [C_in, H + 2p, W + 2p, 1]
        out = conv_valid(lhs, cotangent[:, :, None, :])  # [C_in, k, k, C_out]
        return out.transpose(1, 2, 0, 3)
    # Correlating the padded cotangent with the image gives the flipped gradient.
    padded = jnp.pad(cotangent, ((pad, pad), (pad, pad), (0, 0)))
    lhs = padded.transpose(2, 0, 1)[..., None]  # [C_out, H + 2p, W + 2p, 1]
    out = conv_valid(lhs, image[:, :, None, :])  # [C_out, k, k, C_in]
    return jnp.flip(out.transpose(1, 2, 3, 0), (0, 1))


def _kernel_grad_sliced(image: jax.Array, cotangent: jax.Array, kernel: jax.Array) -> jax.Array:
    """`_kernel_grad_conv` over slices of at most `XLA_CONV_CHANNELS` (16) input and
    output channels, so that XLA runs every conv with its own code: YNNPACK's code for
    this shape (an H x W filter, a k x k output) is 5-6x slower. The head (one output
    channel) stays one conv, which YNNPACK runs faster. One core of the 2-core AMD EPYC,
    192x256: 6 -> 20 channels 7.9 ms (per-tap matmuls 9.6, the unsliced conv 42),
    20 -> 10 10.9 ms (35, 67), 10 -> 20 11.0 ms (17, 68), 20 -> 1 unsliced 2.0 ms
    (sliced 2.8).
    """
    c_in, c_out = kernel.shape[2:]
    if min(c_in, c_out) == 1:
        return _kernel_grad_conv(image, cotangent, kernel)

    def slices(count: int) -> list[slice]:
        step = XLA_CONV_CHANNELS
        return [slice(start, start + step) for start in range(0, count, step)]

    # jnp.block joins the inner lists along C_out (the last axis), the rows along C_in.
    return jnp.block(
        [
            [
                _kernel_grad_conv(image[..., i], cotangent[..., o], kernel[:, :, i, o])
                for o in slices(c_out)
            ]
            for i in slices(c_in)
        ]
    )


def _nhwc_backend(kernel_grad, conv_one=conv_single) -> _StackBackend:
    """NHWC pieces with `conv_one` as one example's conv (forward and input gradient)."""
    return _StackBackend(
        to_layout=lambda x: x,
        from_layout=lambda x: x,
        forward=lambda image, kernel, bias: conv_one(image, kernel) + bias,
        kernel_grad=kernel_grad,
        input_grad=functools.partial(input_grad_conv, conv_one=conv_one),
        bias_grad=lambda cotangent: cotangent.sum((0, 1)),
    )


def _planar_patches(image: jax.Array, kernel_size: int) -> jax.Array:
    """im2col in channel-major layout: [C, H, W] -> [k*k*C, H*W], rows ordered (dy, dx, c)."""
    channels, height, width = image.shape
    pad = kernel_size // 2
    padded = jnp.pad(image, ((0, 0), (pad, pad), (pad, pad)))
    taps = [
        padded[:, dy : dy + height, dx : dx + width]
        for dy in range(kernel_size)
        for dx in range(kernel_size)
    ]
    return jnp.stack(taps).reshape(kernel_size * kernel_size * channels, height * width)


def _planar_forward(image: jax.Array, kernel: jax.Array, bias: jax.Array) -> jax.Array:
    """[C_in, H, W] -> [C_out, H, W] as kernel [C_out, k*k*C_in] @ patches [k*k*C_in, HW]."""
    kernel_size, _, c_in, c_out = kernel.shape
    matrix = kernel.reshape(kernel_size * kernel_size * c_in, c_out).T
    out = matrix @ _planar_patches(image, kernel_size) + bias[:, None]
    return out.reshape(c_out, *image.shape[1:])


def _planar_kernel_grad(image: jax.Array, cotangent: jax.Array, kernel: jax.Array) -> jax.Array:
    """[C_in, H, W], [C_out, H, W] -> [k, k, C_in, C_out] as patches @ cotangent^T."""
    patches = _planar_patches(image, kernel.shape[0])
    return (patches @ cotangent.reshape(cotangent.shape[0], -1).T).reshape(kernel.shape)


def _planar_input_grad(cotangent: jax.Array, kernel: jax.Array) -> jax.Array:
    """[C_out, H, W] -> [C_in, H, W]: the conv with the flipped, io-transposed kernel."""
    flipped = jnp.flip(kernel, (0, 1)).swapaxes(2, 3)
    return _planar_forward(cotangent, flipped, jnp.zeros((kernel.shape[2],), kernel.dtype))


_PLANAR_BACKEND = _StackBackend(
    to_layout=lambda x: x.transpose(0, 3, 1, 2),
    from_layout=lambda x: x.transpose(0, 2, 3, 1),
    forward=_planar_forward,
    kernel_grad=_planar_kernel_grad,
    input_grad=_planar_input_grad,
    bias_grad=lambda cotangent: cotangent.sum((1, 2)),
)


def _make_fused_stack(backend: _StackBackend, slopes: tuple[float | None, ...]):
    """custom_vjp function (convs [(kernel, bias), ...], inputs [B, H, W, C]) -> outputs.

    Layer i is followed by a LeakyReLU of slope `slopes[i]`, or by nothing when None.
    """

    def activate(pre: jax.Array, slope: float | None) -> jax.Array:
        return pre if slope is None else jax.nn.leaky_relu(pre, slope)

    def forward_example(args):
        image, convs = args
        outputs = []
        for (kernel, bias), slope in zip(convs, slopes, strict=True):
            image = activate(backend.forward(image, kernel, bias), slope)
            outputs.append(image)
        return outputs

    def run_forward(convs, inputs):
        return lax.map(forward_example, (backend.to_layout(inputs), convs))

    @jax.custom_vjp
    def stack(convs, inputs):
        # Inference keeps no intermediate activations.
        last_output = lambda args: forward_example(args)[-1]
        layout_inputs = backend.to_layout(inputs)
        return backend.from_layout(lax.map(last_output, (layout_inputs, convs)))

    def stack_fwd(convs, inputs):
        convs_value = jax.tree.map(lambda leaf: leaf.value, convs)
        outputs = run_forward(convs_value, inputs.value)
        # An empty marker in the residuals when the input's cotangent is needed; None
        # (no leaf) when the input is data, so its gradient conv is never computed.
        marker = jnp.zeros((0,)) if inputs.perturbed else None
        residuals = (convs_value, inputs.value, outputs, marker)
        return backend.from_layout(outputs[-1]), residuals

    def stack_bwd(residuals, cotangent):
        convs, inputs, outputs, marker = residuals
        need_input_grad = marker is not None

        def backward_example(args):
            image, convs, outputs, cotangent = args
            conv_inputs = [image, *outputs[:-1]]
            kernel_grads, bias_grads = [], []
            for index in reversed(range(len(convs))):
                kernel = convs[index][0]
                slope = slopes[index]
                pre_grad = (
                    cotangent
                    if slope is None
                    else leaky_relu_grad(outputs[index], cotangent, slope)
                )
                kernel_grads.append(backend.kernel_grad(conv_inputs[index], pre_grad, kernel))
                bias_grads.append(backend.bias_grad(pre_grad))
                if index > 0 or need_input_grad:
                    cotangent = backend.input_grad(pre_grad, kernel)
            grads = list(zip(kernel_grads[::-1], bias_grads[::-1], strict=True))
            return grads, (cotangent if need_input_grad else None)

        cotangent = backend.to_layout(cotangent)
        conv_grads, input_grad = lax.map(
            backward_example, (backend.to_layout(inputs), convs, outputs, cotangent)
        )
        if need_input_grad:
            input_grad = backend.from_layout(input_grad)
        return conv_grads, input_grad

    stack.defvjp(stack_fwd, stack_bwd, symbolic_zeros=True)
    return stack


def _fused(backend: _StackBackend):
    def formulation(filter_banks, inputs, negative_slope, head):
        convs = [(bank.kernel, bank.bias) for bank in filter_banks]
        slopes = [float(negative_slope)] * len(convs)
        if head is not None:
            # The shared head joins the per-example stack, so each example's last
            # activations are still in cache when it runs; the broadcast's transpose
            # sums its per-example gradients over the batch.
            batch_size = inputs.shape[0]
            convs.append(
                (
                    jnp.broadcast_to(head.kernel, (batch_size, *head.kernel.shape)),
                    jnp.broadcast_to(head.bias, (batch_size, *head.bias.shape)),
                )
            )
            slopes.append(None)
        return _make_fused_stack(backend, tuple(slopes))(convs, inputs)

    return formulation


FORMULATIONS: dict[str, Callable[..., jax.Array]] = {
    "vmap": _vmap_formulation,
    # lax.map over examples of the whole stack: plain convs, or im2col + one matmul each.
    "map_conv": _mapped_stack(conv_single),
    "map_im2col": _mapped_stack(im2col_conv_single),
    "shifted": _shifted_formulation,
    # custom_vjp, lax.map of the stack: conv forward and input gradient; kernel gradient
    # as a plain conv with channels as batch ("fused"), as k*k per-tap matmuls over
    # pixels ("fused_taps") or as one im2col matmul ("fused_im2col").
    "fused": _fused(_nhwc_backend(_kernel_grad_conv)),
    "fused_taps": _fused(_nhwc_backend(_kernel_grad_taps)),
    "fused_im2col": _fused(_nhwc_backend(_kernel_grad_im2col)),
    # "fused" with 5-15 output channels of a conv padded to a multiple of 8 (the same
    # values) and the kernel gradient's conv over slices of at most 16 channels.
    "fused_aligned": _fused(_nhwc_backend(_kernel_grad_sliced, aligned_conv_single)),
    # custom_vjp, lax.map of the stack in channel-major layout, everything as
    # [C_out, k*k*C_in] x [k*k*C_in, H*W] matmuls.
    "fused_planar": _fused(_PLANAR_BACKEND),
}

# Default formulation per platform. CPU, measured: `python -m experiments.benchmark` on
# the 2-core AMD EPYC (2 CPU devices, 256x192, the final conv as the head, XLA's
# reductions out of YNNPACK as `gld` sets) timed the batch-16 Adam step at 1.06-1.10 s
# with "fused_aligned" against 1.73 "fused_taps", 2.21 "fused_im2col", 2.27
# "fused_planar" and 2.40 "fused" (PyTorch eager 2.04-2.14 s, compiled 1.96-2.02 in the
# same run); the main job's step (128x96) at 336-373 ms against 480 with "fused".
# Earlier, on another 2-core machine: "fused" 1.21-1.30 s, "fused_taps" 1.29,
# "fused_im2col" 1.82, "fused_planar" 2.20, "map_im2col" 2.33, "shifted" 2.69, "map_conv"
# 4.7 and "vmap" 31. GPU, measured on an H200: "vmap" (one grouped convolution, which
# cuDNN runs natively) has the fastest train step and forward throughput.
_DEFAULT_FORMULATIONS = {"cpu": "fused_aligned", "gpu": "vmap", "cuda": "vmap", "rocm": "vmap"}


def default_formulation(backend: str | None = None) -> str:
    """Name of the default formulation on `backend` ('cpu', 'gpu'; None = JAX's default)."""
    backend = jax.default_backend() if backend is None else backend
    return _DEFAULT_FORMULATIONS.get(backend, "vmap")


def apply_filter_banks(
    filter_banks: Sequence[FilterBank],
    inputs: jax.Array,
    *,
    head: SharedConv | None = None,
    formulation: str | None = None,
    negative_slope: float = layers.NEGATIVE_SLOPE,
) -> jax.Array:
    """Applies per-example filter banks, each followed by a LeakyReLU, then a shared head.

    Args:
      filter_banks: banks with kernel [B, k, k, C_in, C_out] and bias [B, C_out];
        each bank's C_in is the previous bank's C_out.
      inputs: [B, H, W, C_in] (the local network's [flow, x, y]).
      head: optional conv shared by the whole batch (kernel [k, k, C_out, C_head], bias
        [C_head]) applied to the last bank's output with no activation: the local
        network's final conv. The fused formulations run it inside their per-example
        pass, which on CPU is about 3x faster than a separate batched conv with one
        output channel.
      formulation: a key of `FORMULATIONS`; None = `default_formulation()`.
      negative_slope: LeakyReLU slope applied after every bank.

    Returns:
      [B, H, W, C_out of the last bank], or [B, H, W, C_head] with a head; 'SAME'
      padding, stride 1.
    """
    name = default_formulation() if formulation is None else formulation
    if name not in FORMULATIONS:
        raise ValueError(f"unknown formulation {name!r}; choose one of {sorted(FORMULATIONS)}")
    if inputs.ndim != 4:
        raise ValueError(f"inputs must be [B, H, W, C], got shape {inputs.shape}")
    if not filter_banks:
        raise ValueError("filter_banks is empty")
    channels = inputs.shape[-1]
    for index, bank in enumerate(filter_banks):
        kernel, bias = bank.kernel, bank.bias
        if kernel.ndim != 5 or kernel.shape[1] != kernel.shape[2] or kernel.shape[1] % 2 == 0:
            raise ValueError(
                f"filter_banks[{index}].kernel must be [B, k, k, C_in, C_out] with odd k, "
                f"got shape {kernel.shape}"
            )
        if kernel.shape[0] != inputs.shape[0] or kernel.shape[3] != channels:
            raise ValueError(
                f"filter_banks[{index}].kernel shape {kernel.shape} does not match "
                f"batch {inputs.shape[0]} and {channels} input channels (inputs {inputs.shape})"
            )
        if bias.shape != (kernel.shape[0], kernel.shape[4]):
            raise ValueError(
                f"filter_banks[{index}].bias must be {(kernel.shape[0], kernel.shape[4])}, "
                f"got shape {bias.shape}"
            )
        channels = kernel.shape[4]
    if head is not None:
        kernel, bias = head.kernel, head.bias
        if kernel.ndim != 4 or kernel.shape[0] != kernel.shape[1] or kernel.shape[0] % 2 == 0:
            raise ValueError(
                f"head.kernel must be [k, k, C_in, C_out] with odd k, got shape {kernel.shape}"
            )
        if kernel.shape[2] != channels:
            raise ValueError(
                f"head.kernel shape {kernel.shape} does not match the last bank's "
                f"{channels} output channels"
            )
        if bias.shape != (kernel.shape[3],):
            raise ValueError(f"head.bias must be {(kernel.shape[3],)}, got shape {bias.shape}")
    formulation_fn = functools.partial(FORMULATIONS[name], negative_slope=negative_slope)
    apply = lambda banks, inputs, head: formulation_fn(banks, inputs, head=head)
    return on_batch_shards(apply, inputs.shape[0], replicated=(2,))(
        list(filter_banks), inputs, head
    )
