"""The global-local model F(I1, I2, w): global encoder -> hypernetwork -> local network.

The global module sees the image pair and the flow and emits a 6-vector of global
parameters; a linear layer turns it into three 3x3 filter banks (20, 10, 20 output
channels); those banks, applied per example to [flow, x, y], and a final shared 3x3
conv produce the inverse depth. The paper's numbers are the defaults, and each
ablation of the paper's Table (image pair, CoordConv, global module, flow) is a switch.
"""

from __future__ import annotations

from collections.abc import Sequence

import flax.linen as nn
import jax
import jax.numpy as jnp

from gld import baselines, geometry, layers
from gld.global_encoder import GlobalEncoder
from gld.hypernet import FilterBank, HyperNetwork, StaticFilterBanks, apply_filter_banks


class GlobalLocal(nn.Module):
    """The paper's global-local network.

    Attributes:
      encoder_channels, encoder_strides: hidden conv layers of the global encoder.
      global_dim: size of the global parameter vector g.
      bank_channels: output channels of the generated 3x3 filter banks.
      kernel_size: spatial size of the generated filters and the final conv.
      use_image_pair: feed the images to the global module (ablation: flow only).
      use_coordinates: append x, y in [-1, 1] to the local input (ablation: no CoordConv).
      use_global_module: generate filters from g (ablation: static learned filters).
      use_flow: use optical flow (ablation: the image pair replaces the flow everywhere).
      local_flow_units: "normalised" divides the local network's flow by the image size,
        like the global input; "pixels" feeds it in pixels, as the PyTorch reference does
        (on gld_scenes/small it learned slower: test Abs-Inv 0.0382 vs 0.0336 at step 1000).
      filter_formulation: how per-example banks are applied (see `gld.hypernet`);
        None picks the fastest for the platform.
    """

    encoder_channels: Sequence[int] = (16, 32, 64, 128, 256)
    encoder_strides: Sequence[int] = (2, 2, 2, 2, 1)
    global_dim: int = 6
    bank_channels: Sequence[int] = (20, 10, 20)
    kernel_size: int = 3
    use_image_pair: bool = True
    use_coordinates: bool = True
    use_global_module: bool = True
    use_flow: bool = True
    local_flow_units: str = "normalised"
    filter_formulation: str | None = None

    @property
    def local_in_channels(self) -> int:
        """Channels of the local network's input."""
        return (2 if self.use_flow else 6) + (2 if self.use_coordinates else 0)

    @nn.compact
    def __call__(
        self, image1: jax.Array, image2: jax.Array, flow: jax.Array, *, train: bool = False
    ) -> dict[str, jax.Array]:
        """Predicts inverse depth for view 1.

        Args:
          image1, image2: [B, H, W, 3] float32 in [-0.5, 0.5].
          flow: [B, H, W, 2] pixels, I1 -> I2.
          train: unused (no dropout or batch norm); part of the shared model signature.

        Returns:
          {"inv_depth": [B, H, W] positive, "depth": [B, H, W],
           "global_params": [B, global_dim] (zeros without a global module),
           "filter_banks": list of FilterBank(kernel [B, k, k, C_in, C_out], bias [B, C_out])}.
        """
        del train
        _check_inputs(image1, image2, flow)
        batch_size, height, width, _ = flow.shape
        image_pair = jnp.concatenate([image1, image2], axis=-1)
        normalised_flow = layers.normalise_flow(flow)

        if self.local_flow_units not in ("pixels", "normalised"):
            raise ValueError(
                f"local_flow_units must be 'pixels' or 'normalised', got {self.local_flow_units!r}"
            )
        if self.use_flow:
            local_inputs = flow if self.local_flow_units == "pixels" else normalised_flow
            global_inputs = (
                jnp.concatenate([image_pair, normalised_flow], axis=-1)
                if self.use_image_pair
                else normalised_flow
            )
        else:
            local_inputs = image_pair
            global_inputs = image_pair
        if self.use_coordinates:
            coordinates = geometry.normalised_coordinates(height, width, jnp)
            coordinates = jnp.broadcast_to(coordinates, (batch_size, height, width, 2))
            local_inputs = jnp.concatenate([local_inputs, coordinates.astype(flow.dtype)], -1)

        bank_kwargs = dict(
            in_channels=self.local_in_channels,
            bank_channels=tuple(self.bank_channels),
            kernel_size=self.kernel_size,
        )
        if self.use_global_module:
            global_params = GlobalEncoder(
                channels=tuple(self.encoder_channels),
                strides=tuple(self.encoder_strides),
                global_dim=self.global_dim,
                kernel_size=self.kernel_size,
                name="global_encoder",
            )(global_inputs)
            filter_banks = HyperNetwork(**bank_kwargs, name="hypernet")(global_params)
        else:
            global_params = jnp.zeros((batch_size, self.global_dim), flow.dtype)
            filter_banks = StaticFilterBanks(**bank_kwargs, name="static_filters")(batch_size)

        final_conv = ConvParameters(
            in_channels=self.bank_channels[-1],
            out_channels=1,
            kernel_size=self.kernel_size,
            name="final_conv",
        )()
        logits = apply_filter_banks(
            filter_banks, local_inputs, head=final_conv, formulation=self.filter_formulation
        )
        outputs = layers.depth_outputs(logits)
        outputs["global_params"] = global_params
        outputs["filter_banks"] = list(filter_banks)
        return outputs


class ConvParameters(nn.Module):
    """The kernel and bias of a conv shared by the batch, initialised like `nn.Conv`.

    The local network's final conv is applied by `apply_filter_banks` (as its head,
    next to the per-example banks), so the model holds only its parameters; names and
    initialisation are those of `nn.Conv`.
    """

    in_channels: int
    out_channels: int
    kernel_size: int = 3

    @nn.compact
    def __call__(self) -> FilterBank:
        """Returns FilterBank(kernel [k, k, C_in, C_out], bias [C_out])."""
        shape = (self.kernel_size, self.kernel_size, self.in_channels, self.out_channels)
        kernel = self.param("kernel", nn.initializers.lecun_normal(), shape)
        bias = self.param("bias", nn.initializers.zeros_init(), (self.out_channels,))
        return FilterBank(kernel=kernel, bias=bias)


def _check_inputs(image1: jax.Array, image2: jax.Array, flow: jax.Array) -> None:
    for name, array, channels in (("image1", image1, 3), ("image2", image2, 3), ("flow", flow, 2)):
        if array.ndim != 4 or array.shape[-1] != channels:
            raise ValueError(f"{name} must be [B, H, W, {channels}], got shape {array.shape}")
    if not image1.shape[:3] == image2.shape[:3] == flow.shape[:3]:
        raise ValueError(
            f"image1 {image1.shape}, image2 {image2.shape} and flow {flow.shape} must share "
            "batch size and image size"
        )


# Every learned depth network, by name (`--model`).
MODELS: dict[str, type[nn.Module]] = {"global_local": GlobalLocal, **baselines.LEARNED}

# Architecture fields of GlobalLocal that launchers expose as flags.
ARCHITECTURE_FIELDS = (
    "encoder_channels",
    "encoder_strides",
    "global_dim",
    "bank_channels",
    "kernel_size",
    "use_image_pair",
    "use_coordinates",
    "use_global_module",
    "use_flow",
    "local_flow_units",
)


def make_model(name: str = "global_local", **config) -> nn.Module:
    """Builds a registered model; `config` holds its constructor arguments."""
    if name not in MODELS:
        raise ValueError(f"unknown model {name!r}; valid: {sorted(MODELS)}")
    return MODELS[name](**config)


def parameter_counts(params) -> dict[str, int]:
    """Parameters per top-level module and in total."""
    counts = {
        name: sum(int(x.size) for x in jax.tree_util.tree_leaves(subtree))
        for name, subtree in params.items()
    }
    counts["total"] = sum(counts.values())
    return counts
