"""What an exported model is in either file format: its inputs, outputs and metadata.

Both exporters (`gld.inference.export`: `jax.export`; `gld.inference.onnx_export`: ONNX)
take the same model at a fixed image size, check their arguments alike
(`check_arguments`: the platforms, the batch size, the per-example filter formulation,
what the model reads) and describe it alike (`describe`): its inputs (images, flow and
the `EXTRA_INPUTS` a model may read), its outputs (`inference_outputs`), the training
resolution, the depth units, the model and its configuration.
"""

from __future__ import annotations

import dataclasses
import datetime
import json
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import flax.linen as nn
import jax
import numpy as np

import gld
from gld import flow as flow_lib
from gld.models import filter_banks, registry

# Platforms `jax.export` lowers for; a file may hold several (multi-platform lowering).
PLATFORMS = ("cpu", "cuda", "rocm", "tpu")
INPUT_NAMES = ("image1", "image2", "flow")
# Inputs a model may read besides the images and flow (`GlobalLocal.extra_inputs`), each
# with its shape after the batch axis and what to give.
_RELATIVE_POSE = "X2 = R X1 + t: a point in camera 1's frame in camera 2's"
EXTRA_INPUTS = {
    "rotation": ((3, 3), f"the pair's relative rotation R (odometry), {_RELATIVE_POSE}"),
    "translation": ((3,), f"the pair's relative translation t (odometry), {_RELATIVE_POSE}"),
    "flow_rotation": (
        (3, 3),
        f"R of the essential-matrix pose of the input flow (gld.flow_pose), {_RELATIVE_POSE}",
    ),
    "flow_translation": (
        (3,),
        "unit t of the essential-matrix pose of the input flow (gld.flow_pose); " + _RELATIVE_POSE,
    ),
    "intrinsics1": (
        (4,),
        "camera 1 at the exported resolution, normalised: [fx / width, fy / height, "
        "(cx + 0.5) / width, (cy + 0.5) / height] (pixel-index cx, cy)",
    ),
    "intrinsics2": ((4,), "camera 2, normalised as intrinsics1"),
}
DEPTH_UNITS = (
    "baseline: depth in units of the distance between the two camera centres "
    "(the training scale, ||t|| = 1); metric depth = depth * baseline"
)


def check_platforms(platforms: Sequence[str]) -> tuple[str, ...]:
    """The platforms as a tuple; ValueError naming an unknown or repeated one."""
    platforms = tuple(platforms)
    if not platforms:
        raise ValueError(f"platforms is empty; choose from {PLATFORMS}")
    unknown = [platform for platform in platforms if platform not in PLATFORMS]
    if unknown:
        raise ValueError(f"unknown platform(s) {unknown}; valid: {PLATFORMS}")
    if len(set(platforms)) != len(platforms):
        raise ValueError(f"platforms {list(platforms)} lists a platform twice")
    return platforms


def choose_formulation(
    formulation: str | None, platforms: Sequence[str], batch_size: int | None
) -> str:
    """The per-example filter formulation of an export.

    None picks the first platform's default (`filter_banks.default_formulation`). The
    "vmap" formulation is a grouped convolution whose group count is the batch size,
    which `jax.export` cannot make symbolic: with a symbolic batch the default becomes
    "shifted" (the whole batch at once, like "vmap", as batched matmuls), and an
    explicit "vmap" is refused.
    """
    if formulation is not None and formulation not in filter_banks.FORMULATIONS:
        raise ValueError(
            f"unknown formulation {formulation!r}; "
            f"choose one of {sorted(filter_banks.FORMULATIONS)}"
        )
    if formulation == "vmap" and batch_size is None:
        raise ValueError(
            "formulation 'vmap' needs a fixed batch size (its grouped convolution cannot "
            "have a symbolic group count): give a batch size (--batch_size) or another formulation"
        )
    if formulation is not None:
        return formulation
    chosen = filter_banks.default_formulation(platforms[0])
    return "shifted" if chosen == "vmap" and batch_size is None else chosen


def model_name(model: nn.Module) -> str:
    """The registry name (`gld.models.registry.MODELS`) of a model instance."""
    for name, cls in registry.MODELS.items():
        if type(model) is cls:
            return name
    raise ValueError(f"{type(model).__name__} is not a model of gld.models.registry.MODELS")


def model_config(model: nn.Module) -> dict[str, Any]:
    """Every constructor argument of `model`, JSON-ready (tuples as lists)."""
    values = {
        field.name: getattr(model, field.name)
        for field in dataclasses.fields(model)
        if field.name not in ("parent", "name")
    }
    return json.loads(json.dumps(values, default=list))


def model_extra_inputs(model: nn.Module) -> tuple[str, ...]:
    """What `model` reads by keyword besides the images and flow (`EXTRA_INPUTS` keys)."""
    return tuple(getattr(model, "extra_inputs", ()))


def estimates_own_flow(model: nn.Module) -> bool:
    """Whether `model` computes its flow from the images (its flow input only sets the shape)."""
    return callable(getattr(model, "estimate_flow", None))


def check_flow(model: nn.Module, flow: dict[str, Any] | None, flow_network: Any) -> dict[str, Any]:
    """The metadata's "flow": how a runtime computes the model's input flow.

    {"estimator": "model"} for a model that estimates its own; otherwise `flow`, by
    default OpenCV DIS (`gld.flow.runtime_settings`), whose classical settings must be
    this gld's; {"estimator": "flow_net", ...} needs the network (`flow_network`).
    """
    if estimates_own_flow(model):
        if flow_network is not None:
            raise ValueError(f"model {model_name(model)!r} estimates its own flow: no flow network")
        return {"estimator": "model", "help": "the model's own flow network, in model.jaxexport"}
    flow = dict(flow or flow_lib.runtime_settings(flow_lib.DEFAULT_ESTIMATOR))
    estimator = flow.get("estimator")
    if estimator == "flow_net":
        if flow_network is None:
            raise ValueError("a 'flow_net' flow is exported with its network (flow_network=)")
        return flow
    if flow_network is not None:
        raise ValueError(f"flow {estimator!r} is not a flow network's: no flow_network")
    if estimator not in flow_lib.RUNTIME_SETTINGS:
        raise ValueError(
            f"flow estimator {estimator!r} cannot run in an exported model; valid: "
            f"{sorted(flow_lib.RUNTIME_SETTINGS)} or 'flow_net'"
        )
    expected = flow_lib.runtime_settings(estimator)
    if flow != expected:
        raise ValueError(f"flow {flow} is not how this gld runs {estimator!r}: {expected}")
    return flow


def check_arguments(
    model: nn.Module,
    output: str | Path,
    height: int,
    width: int,
    batch_size: int | None,
    formulation: str | None,
    platforms: tuple[str, ...],
    extra_allowed: bool = True,
) -> tuple[nn.Module, str, Path]:
    """Refuses bad arguments; the model with its formulation set, its name, the path."""
    output = Path(output)
    for name, value in (("height", height), ("width", width)):
        if not isinstance(value, int | np.integer) or value < 1:
            raise ValueError(f"{name} must be a positive integer, got {value!r}")
    if batch_size is not None and (not isinstance(batch_size, int | np.integer) or batch_size < 1):
        raise ValueError(f"batch_size must be a positive integer or None, got {batch_size!r}")
    name = model_name(model)
    extra = list(model_extra_inputs(model))
    if extra and not extra_allowed:
        raise ValueError(
            f"model {name!r} also reads {extra} (a given pose or the cameras); only models "
            "of the images and flow convert to ONNX (the jax.export file takes them)"
        )
    unknown = [key for key in extra if key not in EXTRA_INPUTS]
    if unknown:
        raise ValueError(f"model {name!r} reads {unknown}, which no exported file can take")
    if hasattr(model, "filter_formulation"):
        formulation = choose_formulation(formulation, platforms, batch_size)
        model = model.clone(filter_formulation=formulation)
    elif formulation is not None:
        raise ValueError(f"model {name!r} has no per-example filters to give a formulation")
    if output.is_dir():
        raise ValueError(f"output {output} is a directory; give a file name")
    return model, name, output


def inference_outputs(outputs: dict[str, Any]) -> dict[str, jax.Array]:
    """The outputs of `model.apply` that an exported model returns, by name."""
    # Only arrays with a batch axis: filter banks and multi-scale pyramids are training aids.
    return {
        key: value
        for key, value in outputs.items()
        if isinstance(value, jax.Array) and value.ndim >= 1 and key != "filter_banks"
    }


def describe(
    model: nn.Module,
    name: str,
    height: int,
    width: int,
    batch_size: int | None,
    outputs: dict[str, Any],
    source: dict[str, Any] | None,
) -> dict[str, Any]:
    """The metadata both formats share: model, resolution, inputs, outputs, units."""
    batch_dim = "batch" if batch_size is None else int(batch_size)
    extra_inputs = model_extra_inputs(model)
    image_help = "RGB, float32 in [0, 1] = uint8 / 255 (gld.inference.deploy also takes uint8)"
    image = {"dtype": "float32", "range": [0.0, 1.0], "help": image_help}
    return {
        "model": name,
        "model_config": model_config(model),
        "height": int(height),
        "width": int(width),
        "batch_size": None if batch_size is None else int(batch_size),
        "formulation": getattr(model, "filter_formulation", None),
        "inputs": [
            {"name": "image1", "shape": [batch_dim, height, width, 3], **image},
            {"name": "image2", "shape": [batch_dim, height, width, 3], **image},
            {
                "name": "flow",
                "shape": [batch_dim, height, width, 2],
                "dtype": "float32",
                "help": "optical flow image1 -> image2 in pixels at height x width "
                "(pixel p of image1 sits at p + flow(p) in image2)",
            },
            *[
                {
                    "name": key,
                    "shape": [batch_dim, *EXTRA_INPUTS[key][0]],
                    "dtype": "float32",
                    "help": EXTRA_INPUTS[key][1],
                }
                for key in extra_inputs
            ],
        ],
        "extra_inputs": list(extra_inputs),
        "outputs": [
            {
                "name": key,
                "shape": [batch_dim, *[int(d) for d in value.shape[1:]]],
                "dtype": str(value.dtype),
            }
            for key, value in outputs.items()
        ],
        "depth_units": DEPTH_UNITS,
        "gld_version": gld.__version__,
        "jax_version": jax.__version__,
        "exported_at": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
        "source": source,
    }
