"""A trained model converted to ONNX (with the optional jax2onnx), checked against JAX first."""

from __future__ import annotations

import importlib.metadata
import json
from pathlib import Path
from typing import Any

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np

from gld import files as files_lib
from gld.inference import export_interface


def export_onnx(
    model: nn.Module,
    variables: dict,
    output: str | Path,
    *,
    height: int,
    width: int,
    batch_size: int | None = None,
    formulation: str | None = None,
    source: dict[str, Any] | None = None,
    tolerance: float = 1e-4,
    seed: int = 0,
) -> dict[str, Any]:
    """Converts the forward pass to ONNX with jax2onnx, checked against JAX before writing.

    The weights become the ONNX graph's initialisers; inputs are named image1, image2
    and flow, outputs as the model's (inv_depth, depth, global_params), the batch axis
    "batch" unless fixed. The metadata of `gld.inference.export.export_model` (less the
    weights) is stored as the model's metadata property "gld". The converter is an
    optional dependency (`pip install jax2onnx onnxruntime`).

    The converted graph is run with onnxruntime on random pairs and compared with
    `model.apply`; a difference above `tolerance` (absolute, on any output) refuses the
    export. "vmap" is refused outright: jax2onnx 0.17.1 converted its grouped
    convolution into a graph that runs but is wrong (inverse depth off by 0.1 on a tiny
    model), so every other formulation is preferred for ONNX.

    Args:
      model, variables, output, height, width, batch_size, formulation, source: as
        for `gld.inference.export.export_model` (the formulation's default is the CPU one).
      tolerance: largest accepted absolute difference to the JAX outputs.
      seed: seeds the random check pairs.

    Returns:
      The metadata stored in the file.
    """
    if formulation == "vmap":
        raise ValueError(
            "formulation 'vmap' cannot be exported to ONNX (jax2onnx converts its grouped "
            "convolution wrongly); choose another formulation"
        )
    model, name, output = export_interface.check_arguments(
        model, output, height, width, batch_size, formulation, ("cpu",), extra_allowed=False
    )
    # Optional dependencies, imported only when converting: the rest of gld never needs them.
    try:
        import jax2onnx
        import onnx
        import onnxruntime
    except ImportError as error:
        raise ImportError(
            f"ONNX export needs the jax2onnx and onnxruntime packages ({error}); "
            "pip install jax2onnx onnxruntime"
        ) from error

    outputs = jax.eval_shape(
        lambda *inputs: export_interface.inference_outputs(model.apply(variables, *inputs)),
        *[jax.ShapeDtypeStruct((1, height, width, c), jnp.float32) for c in (3, 3, 2)],
    )
    names = list(outputs)

    def forward(image1, image2, flow):
        # Images in [0, 1], as every gld predictor takes them; the model reads [-0.5, 0.5].
        results = export_interface.inference_outputs(
            model.apply(variables, image1 - 0.5, image2 - 0.5, flow)
        )
        return tuple(results[key] for key in names)

    batch = "batch" if batch_size is None else int(batch_size)
    proto = jax2onnx.to_onnx(
        forward,
        [(batch, height, width, 3), (batch, height, width, 3), (batch, height, width, 2)],
        model_name=f"gld_{name}",
        input_names=list(export_interface.INPUT_NAMES),
        output_names=names,
    )
    check_batch = 2 if batch_size is None else int(batch_size)
    rng = np.random.default_rng(seed)
    inputs = {
        "image1": rng.uniform(0.0, 1.0, (check_batch, height, width, 3)).astype(np.float32),
        "image2": rng.uniform(0.0, 1.0, (check_batch, height, width, 3)).astype(np.float32),
        "flow": rng.normal(0.0, 2.0, (check_batch, height, width, 2)).astype(np.float32),
    }
    session = onnxruntime.InferenceSession(
        proto.SerializeToString(), providers=["CPUExecutionProvider"]
    )
    converted = dict(zip(names, session.run(names, inputs), strict=True))
    expected = export_interface.inference_outputs(
        model.apply(variables, inputs["image1"] - 0.5, inputs["image2"] - 0.5, inputs["flow"])
    )
    described = f"{name} (formulation {getattr(model, 'filter_formulation', None)!r})"
    for key in names:
        difference = float(np.max(np.abs(converted[key] - np.asarray(expected[key]))))
        if not difference <= tolerance:
            raise ValueError(
                f"the ONNX conversion of {described} differs from JAX by {difference:.3g} "
                f"on {key!r} (tolerance {tolerance}); nothing written: try another formulation"
            )
    metadata = {
        "format": "onnx",
        **export_interface.describe(model, name, height, width, batch_size, outputs, source),
        "onnx_opset": int(proto.opset_import[0].version),
        "jax2onnx_version": importlib.metadata.version("jax2onnx"),
        "onnxruntime_check": {"pairs": check_batch, "tolerance": tolerance},
    }
    entry = proto.metadata_props.add()
    entry.key, entry.value = "gld", json.dumps(metadata)
    files_lib.write_atomically(output, lambda path: onnx.save_model(proto, str(path)))
    return metadata
