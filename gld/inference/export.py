"""A trained model as one `jax.export` file that runs without the training stack.

    from gld.inference import export, workdir_export
    workdir_export.export_workdir("runs/demo", "runs/demo/model.gldx")   # CPU, any batch
    workdir_export.export_workdir("runs/demo", "gpu.gldx", platforms=("cuda",), batch_size=1)
    export.export_model(model, variables, "model.gldx", height=96, width=128)  # a live model

The file is a zip archive of three members:

    metadata.json   what a user needs: inputs (names, shapes, dtypes, normalisation;
                    after the flow, "extra_inputs": the odometry pose, the flow's
                    essential-matrix pose and/or the normalised cameras for models that
                    read them), outputs, the training resolution, depth units, the model and its
                    configuration, the gld and JAX versions, the source workdir and step,
                    and "flow": how the model's input flow is computed from the frames
    model.jaxexport the forward pass serialised by `jax.export` (StableHLO), batch size
                    symbolic unless fixed, image size fixed at the training resolution
    weights.npz     the variables, one array per leaf, in the order metadata "weights" lists

and, for a model trained on a flow network's flow ("flow": {"estimator": "flow_net", ...}),
that network the same way: flow_net.jaxexport and flow_net_weights.npz. Images are RGB in
[0, 1] (uint8 / 255), as every gld predictor takes them.

The variables are arguments of the exported function rather than constants baked into
it: the serialised module stays small whatever the model's size (DispNet's and FCRN's
40-60M parameters would otherwise be hundreds of MB of constants that XLA keeps twice
while compiling), one export serves every checkpoint of the same architecture, and the
weights stay readable with plain numpy. `gld.inference.deploy.DeployedModel` loads them once.

The inputs, outputs and metadata are those of every export (`gld.inference.export_interface`);
`gld.inference.onnx_export` converts the same forward pass to ONNX.
"""

from __future__ import annotations

import io
import json
import zipfile
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np

from gld import files as files_lib
from gld.inference import export_interface

FORMAT = "gld-exported-model"
# 3: images in [0, 1] (before: [-0.5, 0.5]), "flow" in the metadata, and the flow
# network's members; 2: inputs after the flow for models that read a given pose or the
# cameras ("extra_inputs"); version 1 files (images and flow only) read as version 2.
FORMAT_VERSION = 3
METADATA_MEMBER = "metadata.json"
EXPORTED_MEMBER = "model.jaxexport"
WEIGHTS_MEMBER = "weights.npz"
FLOW_EXPORTED_MEMBER = "flow_net.jaxexport"
FLOW_WEIGHTS_MEMBER = "flow_net_weights.npz"


def _weight_names(variables: dict) -> tuple[list[str], list[jax.Array], Any]:
    """Leaf names ("params/global_encoder/conv_0/kernel"), leaves and tree of `variables`."""
    with_paths, tree = jax.tree_util.tree_flatten_with_path(variables)
    names = ["/".join(str(getattr(key, "key", key)) for key in path) for path, _ in with_paths]
    return names, [leaf for _, leaf in with_paths], tree


def _serialised(forward, weights: list[np.ndarray], platforms, *inputs) -> Any:
    """`jax.export` of `forward(weights, *inputs)`, the weights an argument."""
    weight_specs = [jax.ShapeDtypeStruct(weight.shape, weight.dtype) for weight in weights]
    return jax.export.export(jax.jit(forward), platforms=platforms)(weight_specs, *inputs)


def _npz(weights: list[np.ndarray]) -> bytes:
    buffer = io.BytesIO()
    np.savez(buffer, **{f"{i:05d}": weight for i, weight in enumerate(weights)})
    return buffer.getvalue()


def _flow_network_members(flow_network, batch, height, width, platforms) -> dict[str, bytes]:
    """The flow network's members: `flow_network` = (FlowNet, its variables)."""
    network, variables = flow_network
    _, weights, tree = _weight_names(variables)
    weights = [np.asarray(jax.device_get(weight)) for weight in weights]

    def forward(weights, image1, image2):
        variables = jax.tree_util.tree_unflatten(tree, weights)
        return network.apply(variables, image1 - 0.5, image2 - 0.5)["flow"]

    image_spec = jax.ShapeDtypeStruct((batch, height, width, 3), jnp.float32)
    exported = _serialised(forward, weights, platforms, image_spec, image_spec)
    return {FLOW_EXPORTED_MEMBER: bytes(exported.serialize()), FLOW_WEIGHTS_MEMBER: _npz(weights)}


def export_model(
    model: nn.Module,
    variables: dict,
    output: str | Path,
    *,
    height: int,
    width: int,
    platforms: Sequence[str] = ("cpu",),
    batch_size: int | None = None,
    formulation: str | None = None,
    source: dict[str, Any] | None = None,
    flow: dict[str, Any] | None = None,
    flow_network: tuple[nn.Module, dict] | None = None,
) -> dict[str, Any]:
    """Serialises `model.apply(variables, ...)` with `jax.export` into one file.

    Args:
      model: a model of `gld.models.registry.MODELS`.
      variables: its variables ({"params": ..., maybe "batch_stats": ...}).
      output: the file to write (a zip archive; parent folders are created).
      height, width: the image size the model runs at (its training resolution).
      platforms: platforms to lower for (`export_interface.PLATFORMS`); several give one
        multi-platform module that runs on each.
      batch_size: a fixed batch size; None makes it symbolic (any batch size >= 1).
      formulation: how the global-local model applies its per-example filters
        (`gld.models.filter_banks.FORMULATIONS`); None: the pick of
        `export_interface.choose_formulation`. Models without per-example filters refuse a
        formulation.
      source: where the variables come from ({"workdir": ..., "step": ...}), recorded.
      flow: how the runtime computes the model's input flow from the frames
        (`gld.runs.trained_flow.runtime_flow`); None: OpenCV DIS, every dataset's default.
        A model that estimates its own flow records {"estimator": "model"} whatever given.
      flow_network: (FlowNet, variables) of a "flow_net" flow, exported beside the model.

    Returns:
      The metadata written to the file.
    """
    platforms = export_interface.check_platforms(platforms)
    model, name, output = export_interface.check_arguments(
        model, output, height, width, batch_size, formulation, platforms
    )
    weight_names, weights, tree = _weight_names(variables)
    weights = [np.asarray(jax.device_get(weight)) for weight in weights]

    extra_inputs = export_interface.model_extra_inputs(model)

    flow, members = export_interface.check_flow(model, flow, flow_network), {}

    def forward(weights, image1, image2, flow, *extra):
        variables = jax.tree_util.tree_unflatten(tree, weights)
        given = dict(zip(extra_inputs, extra, strict=True))
        return export_interface.inference_outputs(
            model.apply(variables, image1 - 0.5, image2 - 0.5, flow, **given)
        )

    (batch,) = jax.export.symbolic_shape("batch") if batch_size is None else (int(batch_size),)
    image_spec = jax.ShapeDtypeStruct((batch, height, width, 3), jnp.float32)
    flow_spec = jax.ShapeDtypeStruct((batch, height, width, 2), jnp.float32)
    extra_specs = [
        jax.ShapeDtypeStruct((batch, *export_interface.EXTRA_INPUTS[key][0]), jnp.float32)
        for key in extra_inputs
    ]
    exported = _serialised(
        forward, weights, platforms, image_spec, image_spec, flow_spec, *extra_specs
    )
    if flow_network is not None:
        members = _flow_network_members(flow_network, batch, height, width, platforms)
    outputs = jax.tree_util.tree_unflatten(exported.out_tree, exported.out_avals)
    metadata = {
        "format": FORMAT,
        "format_version": FORMAT_VERSION,
        **export_interface.describe(model, name, height, width, batch_size, outputs, source),
        "platforms": list(platforms),
        "flow": flow,
        "weights": [
            {"name": weight_name, "shape": list(weight.shape), "dtype": str(weight.dtype)}
            for weight_name, weight in zip(weight_names, weights, strict=True)
        ],
        "calling_convention": "Exported.call(weights, image1, image2, flow, *extra): weights "
        "is the list of weights.npz arrays in the order of 'weights', extra the arrays "
        "'extra_inputs' names, in its order; returns a dict of 'outputs'",
    }
    members = {
        METADATA_MEMBER: (json.dumps(metadata, indent=1) + "\n").encode(),
        EXPORTED_MEMBER: bytes(exported.serialize()),
        WEIGHTS_MEMBER: _npz(weights),
        **members,
    }

    def write(path: Path) -> None:
        with zipfile.ZipFile(path, "w", zipfile.ZIP_STORED) as archive:
            for name, content in members.items():
                archive.writestr(name, content)

    files_lib.write_atomically(output, write)
    return metadata
