"""The hypernetwork LP: global parameters -> the local network's per-example filter banks.

The paper's local network C_phi is a stack of 3x3 convolutions whose filters are
not learned directly: a single linear layer (the hypernetwork LP) maps each
example's global parameters `g` [B, G] to the weights and biases of every bank.
Every example of a batch is therefore convolved with its own filters, which
`gld.models.filter_banks.apply_filter_banks` applies. `StaticFilterBanks` (the "no global
module" ablation) learns one set of banks for all examples instead.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import flax.linen as nn
import jax
import jax.numpy as jnp

from gld.models import layers
from gld.models.filter_banks import FilterBank

# Fraction of a filter's initial scale by which a unit-variance global parameter
# vector moves it at initialisation: enough that the global module steers the local
# network from the first step, small enough that the filters start as a well-scaled
# (He-initialised) conv stack rather than noise driven by an untrained encoder.
MODULATION_SCALE = 0.2


def _bank_shapes(
    in_channels: int, bank_channels: Sequence[int], kernel_size: int
) -> list[tuple[int, int]]:
    """(C_in, C_out) of every bank."""
    if kernel_size < 1 or kernel_size % 2 == 0:
        raise ValueError(f"kernel_size must be a positive odd number, got {kernel_size}")
    if in_channels < 1 or not bank_channels or min(bank_channels) < 1:
        raise ValueError(
            f"in_channels ({in_channels}) and bank_channels ({tuple(bank_channels)}) "
            "must be positive and bank_channels non-empty"
        )
    channels = [in_channels, *bank_channels]
    return list(zip(channels[:-1], channels[1:], strict=True))


def hypernet_output_size(
    in_channels: int = 4, bank_channels: Sequence[int] = (20, 10, 20), kernel_size: int = 3
) -> int:
    """Number of hypernetwork outputs: every bank's kernel and bias entries.

    With the paper's defaults ([flow, x, y] = 4 input channels, banks of 20, 10, 20
    3x3 filters) this is 4,370 (the paper rounds it to 3.9K).
    """
    return sum(
        kernel_size * kernel_size * c_in * c_out + c_out
        for c_in, c_out in _bank_shapes(in_channels, bank_channels, kernel_size)
    )


def _initial_kernel_std(c_in: int, kernel_size: int) -> float:
    """He-normal standard deviation of a conv followed by a LeakyReLU."""
    gain = 2.0 / (1.0 + layers.NEGATIVE_SLOPE**2)
    return math.sqrt(gain / (kernel_size * kernel_size * c_in))


def _split_banks(
    flat: jax.Array, shapes: Sequence[tuple[int, int]], kernel_size: int
) -> list[FilterBank]:
    """[B, hypernet_output_size] -> banks; the layout is (kernel, bias) per bank."""
    batch_size = flat.shape[0]
    banks, offset = [], 0
    for c_in, c_out in shapes:
        kernel_entries = kernel_size * kernel_size * c_in * c_out
        kernel = flat[:, offset : offset + kernel_entries].reshape(
            batch_size, kernel_size, kernel_size, c_in, c_out
        )
        offset += kernel_entries
        bias = flat[:, offset : offset + c_out]
        offset += c_out
        banks.append(FilterBank(kernel=kernel, bias=bias))
    return banks


def _conv_stack_init(shapes: Sequence[tuple[int, int]], kernel_size: int):
    """Initialiser of the flat vector: He-normal kernels and zero biases per bank."""

    def init(key: jax.Array, shape: Sequence[int], dtype=jnp.float32) -> jax.Array:
        parts = []
        for c_in, c_out in shapes:
            key, bank_key = jax.random.split(key)
            std = _initial_kernel_std(c_in, kernel_size)
            kernel_shape = (kernel_size * kernel_size * c_in * c_out,)
            parts.append(std * jax.random.normal(bank_key, kernel_shape, dtype))
            parts.append(jnp.zeros((c_out,), dtype))
        flat = jnp.concatenate(parts)
        if flat.shape != tuple(shape):
            raise ValueError(f"hypernetwork bias shape {tuple(shape)} != {flat.shape}")
        return flat

    return init


def _modulation_init(
    shapes: Sequence[tuple[int, int]], kernel_size: int, modulation_scale: float = MODULATION_SCALE
):
    """Initialiser of the [G, outputs] kernel: each output column has standard deviation
    `modulation_scale * filter_std / sqrt(G)`, so that unit-variance global parameters
    perturb every filter (and bias) by about `modulation_scale` of the filter scale."""

    def init(key: jax.Array, shape: Sequence[int], dtype=jnp.float32) -> jax.Array:
        global_dim = shape[0]
        column_std = []
        for c_in, c_out in shapes:
            std = modulation_scale * _initial_kernel_std(c_in, kernel_size)
            column_std.append(jnp.full((kernel_size * kernel_size * c_in * c_out + c_out,), std))
        scale = jnp.concatenate(column_std).astype(dtype) / math.sqrt(global_dim)
        if scale.shape[0] != shape[1]:
            raise ValueError(f"hypernetwork kernel shape {tuple(shape)} != (G, {scale.shape[0]})")
        return jax.random.normal(key, tuple(shape), dtype) * scale

    return init


class HyperNetwork(nn.Module):
    """The paper's LP: ONE linear layer, global parameters -> per-example filter banks.

    Initialisation: the layer's bias is the flattened weights of a He-initialised
    static conv stack (zero conv biases), and its kernel is scaled so that a
    unit-variance `global_params` perturbs each generated filter by about
    `modulation_scale` (20% by default) of its initial scale. (An untrained encoder's g
    varies far less than that across pairs unless it is standardised;
    `GlobalLocal.global_norm`.) The generated network thus starts
    as a sensible conv stack that the global parameters modulate rather than swamp,
    which matters when training from one supervised pixel per image.

    Attributes:
      in_channels: channels of the local network's input (flow + x, y = 4).
      bank_channels: output channels of each generated bank.
      kernel_size: odd spatial size of every generated filter.
    """

    in_channels: int = 4
    bank_channels: Sequence[int] = (20, 10, 20)
    kernel_size: int = 3
    modulation_scale: float = MODULATION_SCALE

    @nn.compact
    def __call__(self, global_params: jax.Array) -> list[FilterBank]:
        """global_params: [B, G] -> banks with kernel [B, k, k, C_in, C_out], bias [B, C_out]."""
        if global_params.ndim != 2:
            raise ValueError(f"global_params must be [B, G], got shape {global_params.shape}")
        shapes = _bank_shapes(self.in_channels, self.bank_channels, self.kernel_size)
        flat = nn.Dense(
            hypernet_output_size(self.in_channels, self.bank_channels, self.kernel_size),
            kernel_init=_modulation_init(shapes, self.kernel_size, self.modulation_scale),
            bias_init=_conv_stack_init(shapes, self.kernel_size),
            name="linear",
        )(global_params)
        return _split_banks(flat, shapes, self.kernel_size)


class StaticFilterBanks(nn.Module):
    """Learned filters shared by all examples (the "no global module" ablation).

    Same initialisation as the hypernetwork's conv stack (He-normal, zero bias).
    """

    in_channels: int = 4
    bank_channels: Sequence[int] = (20, 10, 20)
    kernel_size: int = 3

    @nn.compact
    def __call__(self, batch_size: int) -> list[FilterBank]:
        """-> banks with kernel [batch_size, k, k, C_in, C_out] (the same for every example)."""
        shapes = _bank_shapes(self.in_channels, self.bank_channels, self.kernel_size)
        banks = []
        for index, (c_in, c_out) in enumerate(shapes):
            std = _initial_kernel_std(c_in, self.kernel_size)
            kernel = self.param(
                f"kernel_{index}",
                nn.initializers.normal(std),
                (self.kernel_size, self.kernel_size, c_in, c_out),
            )
            bias = self.param(f"bias_{index}", nn.initializers.zeros, (c_out,))
            banks.append(
                FilterBank(
                    kernel=jnp.broadcast_to(kernel, (batch_size, *kernel.shape)),
                    bias=jnp.broadcast_to(bias, (batch_size, c_out)),
                )
            )
        return banks
