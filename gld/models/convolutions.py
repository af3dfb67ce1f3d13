"""Convolution pieces the filter-bank formulations are built from: a batch with one
kernel, one example (also with its output channels aligned to the CPU's vectors),
'SAME' padding, im2col patches, shifted matmuls, the input gradient, and LeakyReLU's
backward pass read off its output; and the conv of the baselines and the flow network
(`conv_general_dilated`, which `gld.models.layers.Conv` runs): a matmul of patches for
an input map smaller than the kernel, lax's conv for any other.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jax import lax

DIMENSION_NUMBERS = ("NHWC", "HWIO", "NHWC")


def conv(inputs: jax.Array, kernel: jax.Array) -> jax.Array:
    """Plain conv of a batch with one shared kernel: [N, H, W, C_in] x [k, k, C_in, C_out]."""
    return lax.conv_general_dilated(
        inputs, kernel, (1, 1), "SAME", dimension_numbers=DIMENSION_NUMBERS
    )


def conv_single(image: jax.Array, kernel: jax.Array) -> jax.Array:
    """One example: [H, W, C_in] x [k, k, C_in, C_out] -> [H, W, C_out]."""
    return conv(image[None], kernel)[0]


# The most input and output channels a conv may have for XLA's CPU runtime (jaxlib 0.10)
# to run it with its own code; it hands a conv with more to YNNPACK (XLA's
# `ynn_support.cc`). Which of the two runs a conv decides its speed.
XLA_CONV_CHANNELS = 16


def aligned_channels(count: int) -> int:
    """`count` output channels rounded up to a multiple of 8 (one AVX vector of float32)
    when there are 5 to 15 of them (`XLA_CONV_CHANNELS`); other counts stay."""
    return count if count <= 4 or count >= XLA_CONV_CHANNELS else -(-count // 8) * 8


def aligned_conv_single(image: jax.Array, kernel: jax.Array) -> jax.Array:
    """`conv_single` with the output channels padded by zero filters to
    `aligned_channels` and cut back: the same values.

    XLA's own code and YNNPACK (`XLA_CONV_CHANNELS`) both run some output counts far
    slower than the next multiple of 8, but YNNPACK runs 20 outputs faster than 24. One
    core of the 2-core AMD EPYC, 192x256: 20 inputs, 10 outputs 19.4 ms, 16
    outputs 8.4; 6 inputs, 10 outputs 10.9 ms, 16 outputs 8.9; 10 inputs, 20 outputs
    5.8 ms, 24 outputs 6.4.
    """
    c_out = kernel.shape[-1]
    padding = aligned_channels(c_out) - c_out
    if not padding:
        return conv_single(image, kernel)
    kernel = jnp.pad(kernel, ((0, 0), (0, 0), (0, 0), (0, padding)))
    return conv_single(image, kernel)[..., :c_out]


def pad_same(images: jax.Array, kernel_size: int) -> jax.Array:
    """Zero-pads the two spatial axes (the third- and second-last) for a 'SAME' conv."""
    pad = kernel_size // 2
    widths = [(0, 0)] * (images.ndim - 3) + [(pad, pad), (pad, pad), (0, 0)]
    return jnp.pad(images, widths)


def shifted_views(images: jax.Array, kernel_size: int) -> list[jax.Array]:
    """The k*k views of zero-padded images [..., H, W, C] that a 'SAME' conv's taps read,
    ordered (dy, dx) like HWIO."""
    height, width = images.shape[-3:-1]
    padded = pad_same(images, kernel_size)
    return [
        padded[..., dy : dy + height, dx : dx + width, :]
        for dy in range(kernel_size)
        for dx in range(kernel_size)
    ]


def shifted_conv(images: jax.Array, kernels: jax.Array) -> jax.Array:
    """Per-example conv as a sum of k*k shifted batched matmuls (no patch tensor).

    images: [B, H, W, C_in]; kernels: [B, k, k, C_in, C_out] -> [B, H, W, C_out].
    """
    kernel_size = kernels.shape[1]
    taps = kernels.reshape(kernels.shape[0], kernel_size * kernel_size, *kernels.shape[3:])
    out = None
    for index, view in enumerate(shifted_views(images, kernel_size)):
        term = jnp.einsum("bhwc,bcd->bhwd", view, taps[:, index])
        out = term if out is None else out + term
    return out


def im2col_patches(image: jax.Array, kernel_size: int) -> jax.Array:
    """im2col of one example: [H, W, C] -> [H, W, k*k*C] ordered (dy, dx, c) like HWIO."""
    return jnp.concatenate(shifted_views(image, kernel_size), axis=-1)


def im2col_conv_single(image: jax.Array, kernel: jax.Array) -> jax.Array:
    """One example as im2col + matmul: [H, W, C_in] x [k, k, C_in, C_out]."""
    kernel_size, _, c_in, c_out = kernel.shape
    patches = im2col_patches(image, kernel_size)
    return patches @ kernel.reshape(kernel_size * kernel_size * c_in, c_out)


def conv_valid(inputs: jax.Array, kernel: jax.Array) -> jax.Array:
    return lax.conv_general_dilated(
        inputs, kernel, (1, 1), "VALID", dimension_numbers=DIMENSION_NUMBERS
    )


def input_grad_conv(cotangent: jax.Array, kernel: jax.Array, conv_one=conv_single) -> jax.Array:
    """NHWC input gradient: `conv_one` (one example's conv) with the flipped,
    io-transposed kernel."""
    return conv_one(cotangent, jnp.flip(kernel, (0, 1)).swapaxes(2, 3))


def leaky_relu_grad(activations: jax.Array, cotangent: jax.Array, slope: float) -> jax.Array:
    """Cotangent through LeakyReLU, read off its output (same sign as its input)."""
    return jnp.where(activations > 0, cotangent, slope * cotangent)


def patches_conv(
    inputs: jax.Array,
    kernel: jax.Array,
    strides: tuple[int, int],
    padding: tuple[tuple[int, int], tuple[int, int]],
    precision=None,
) -> jax.Array:
    """An NHWC x HWIO conv as one matmul of patches: the kernel's rows and columns that
    only ever read the zero padding are left out (a 3x3 conv of a 1x1 map is its centre
    tap alone)."""
    padded = jnp.pad(inputs, ((0, 0), *padding, (0, 0)))
    out_size = [
        (padded.shape[1 + axis] - kernel.shape[axis]) // strides[axis] + 1 for axis in (0, 1)
    ]

    def offsets_read(axis):
        # The kernel offsets along `axis` whose reads (offset, offset + stride, ...) reach
        # the image, which starts `padding[axis][0]` rows (or columns) into the padded map.
        start, size, stride = padding[axis][0], inputs.shape[1 + axis], strides[axis]
        return [
            offset
            for offset in range(kernel.shape[axis])
            if any(start <= offset + stride * i < start + size for i in range(out_size[axis]))
        ]

    rows, columns = offsets_read(0), offsets_read(1)
    views = [
        padded[
            :,
            dy : dy + strides[0] * (out_size[0] - 1) + 1 : strides[0],
            dx : dx + strides[1] * (out_size[1] - 1) + 1 : strides[1],
        ]
        for dy in rows
        for dx in columns
    ]
    if not views:  # a padding so wide that no output reads the image
        return jnp.zeros((inputs.shape[0], *out_size, kernel.shape[-1]), inputs.dtype)
    # The offsets read are consecutive: one slice of the kernel, whose gradient is one pad.
    taps = kernel[rows[0] : rows[-1] + 1, columns[0] : columns[-1] + 1]
    return jnp.matmul(
        jnp.concatenate(views, axis=-1), taps.reshape(-1, kernel.shape[-1]), precision=precision
    )


# How flax describes an NHWC input and an HWIO kernel to `lax.conv_general_dilated`.
_NHWC_HWIO = lax.ConvDimensionNumbers(
    lhs_spec=(0, 3, 1, 2), rhs_spec=(3, 2, 0, 1), out_spec=(0, 3, 1, 2)
)


def conv_general_dilated(
    lhs,
    rhs,
    window_strides,
    padding,
    lhs_dilation=None,
    rhs_dilation=None,
    dimension_numbers=None,
    feature_group_count=1,
    precision=None,
    **kwargs,
):
    """`lax.conv_general_dilated`, but a plain 2-D conv of an input map smaller than its
    kernel on a side is `patches_conv`: the same values up to float32 rounding, and their
    gradients.

    XLA's CPU runtime (jaxlib 0.10) runs a conv of an input smaller than its kernel ~50x
    below its usual rate. One core of the Intel Xeon, batch 2, forward / gradient, lax
    against patches: a 5x5 conv of a 4x4 map, 1024 -> 512 channels (FCRN's first
    up-projection at 64x48), 1,380 / 4,118 ms against 16 / 54; a 3x3 conv of a 1x1 map,
    1024 channels (DispNet's deepest at 64x48), 30 / 114 against 0.6 / 20. Maps as large
    as their kernel or larger stay lax's: patches of every map up to 64 pixels were
    ahead in isolation (8x6, 5x5, 1024 -> 512: 78 / 336 against 60 / 124), but not in
    FCRN's or DispNet's whole train step at 128x96, and their dots added a fifth to the
    compile of the tiny suite's FCRN and DispNet steps (19.0 -> 15.7 s, 11.2 -> 8.4 s
    without them).
    """
    plain = (
        lhs.ndim == 4
        and dimension_numbers in (_NHWC_HWIO, DIMENSION_NUMBERS)
        and all(d == 1 for d in (lhs_dilation or (1, 1)) + tuple(rhs_dilation or (1, 1)))
        and feature_group_count == 1
        and not kwargs
    )
    if plain and (lhs.shape[1] < rhs.shape[0] or lhs.shape[2] < rhs.shape[1]):
        if isinstance(padding, str):
            padding = lax.padtype_to_pads(lhs.shape[1:3], rhs.shape[:2], window_strides, padding)
        return patches_conv(lhs, rhs, tuple(window_strides), tuple(map(tuple, padding)), precision)
    return lax.conv_general_dilated(
        lhs,
        rhs,
        window_strides,
        padding,
        lhs_dilation=lhs_dilation,
        rhs_dilation=rhs_dilation,
        dimension_numbers=dimension_numbers,
        feature_group_count=feature_group_count,
        precision=precision,
        **kwargs,
    )
