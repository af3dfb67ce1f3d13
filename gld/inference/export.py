"""A trained model as one file that runs without the training stack (`gld.inference.deploy`).

    from gld.inference import export
    export.export_workdir("runs/demo", "runs/demo/model.gldx")             # CPU, any batch
    export.export_workdir("runs/demo", "gpu.gldx", platforms=("cuda",), batch_size=1)

The file is a zip archive of three members:

    metadata.json   what a user needs: inputs (names, shapes, dtypes, normalisation;
                    after the flow, "extra_inputs": the odometry pose, the flow's
                    essential-matrix pose or the normalised cameras for models that
                    read them), outputs, the training resolution, depth units, the model and its
                    configuration, the gld and JAX versions, the source workdir and step
    model.jaxexport the forward pass serialised by `jax.export` (StableHLO), batch size
                    symbolic unless fixed, image size fixed at the training resolution
    weights.npz     the variables, one array per leaf, in the order metadata "weights" lists

The variables are arguments of the exported function rather than constants baked into
it: the serialised module stays small whatever the model's size (DispNet's and FCRN's
40-60M parameters would otherwise be hundreds of MB of constants that XLA keeps twice
while compiling), one export serves every checkpoint of the same architecture, and the
weights stay readable with plain numpy. `gld.inference.deploy.DeployedModel` loads them once.

`export_onnx` converts the same forward pass to ONNX with the optional jax2onnx package,
checking the converted graph against JAX with onnxruntime before anything is written.
"""

from __future__ import annotations

import dataclasses
import datetime
import importlib.metadata
import importlib.util
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

import gld
from gld import files as files_lib
from gld.models import filter_banks, registry
from gld.runs import checkpoints as checkpoint_lib
from gld.runs import workdir as workdir_lib

FORMAT = "gld-exported-model"
# 2: inputs after the flow for models that read a given pose or the cameras
# ("extra_inputs"); version 1 files (images and flow only) read the same way.
FORMAT_VERSION = 2
METADATA_MEMBER = "metadata.json"
EXPORTED_MEMBER = "model.jaxexport"
WEIGHTS_MEMBER = "weights.npz"

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


def _extra_inputs(model: nn.Module) -> tuple[str, ...]:
    """What `model` reads by keyword besides the images and flow (`EXTRA_INPUTS` keys)."""
    return tuple(getattr(model, "extra_inputs", ()))


def _weight_names(variables: dict) -> tuple[list[str], list[jax.Array], Any]:
    """Leaf names ("params/global_encoder/conv_0/kernel"), leaves and tree of `variables`."""
    with_paths, tree = jax.tree_util.tree_flatten_with_path(variables)
    names = ["/".join(str(getattr(key, "key", key)) for key in path) for path, _ in with_paths]
    return names, [leaf for _, leaf in with_paths], tree


def _checked(
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
    extra = list(_extra_inputs(model))
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


def _inference_outputs(outputs: dict[str, Any]) -> dict[str, jax.Array]:
    # Only arrays with a batch axis: filter banks and multi-scale pyramids are training aids.
    return {
        key: value
        for key, value in outputs.items()
        if isinstance(value, jax.Array) and value.ndim >= 1 and key != "filter_banks"
    }


def _describe(
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
    extra_inputs = _extra_inputs(model)
    image_help = (
        "RGB, float32 in [-0.5, 0.5] = uint8 / 255 - 0.5 (gld.inference.deploy also takes uint8)"
    )
    image = {"dtype": "float32", "range": [-0.5, 0.5], "help": image_help}
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
) -> dict[str, Any]:
    """Serialises `model.apply(variables, ...)` with `jax.export` into one file.

    Args:
      model: a model of `gld.models.registry.MODELS`.
      variables: its variables ({"params": ..., maybe "batch_stats": ...}).
      output: the file to write (a zip archive; parent folders are created).
      height, width: the image size the model runs at (its training resolution).
      platforms: platforms to lower for (`PLATFORMS`); several give one multi-platform
        module that runs on each.
      batch_size: a fixed batch size; None makes it symbolic (any batch size >= 1).
      formulation: how the global-local model applies its per-example filters
        (`gld.models.filter_banks.FORMULATIONS`); None: `choose_formulation`'s pick. Models
        without per-example filters refuse a formulation.
      source: where the variables come from ({"workdir": ..., "step": ...}), recorded.

    Returns:
      The metadata written to the file.
    """
    platforms = check_platforms(platforms)
    model, name, output = _checked(model, output, height, width, batch_size, formulation, platforms)
    weight_names, weights, tree = _weight_names(variables)
    weights = [np.asarray(jax.device_get(weight)) for weight in weights]

    extra_inputs = _extra_inputs(model)

    def forward(weights, image1, image2, flow, *extra):
        variables = jax.tree_util.tree_unflatten(tree, weights)
        given = dict(zip(extra_inputs, extra, strict=True))
        return _inference_outputs(model.apply(variables, image1, image2, flow, **given))

    (batch,) = jax.export.symbolic_shape("batch") if batch_size is None else (int(batch_size),)
    image_spec = jax.ShapeDtypeStruct((batch, height, width, 3), jnp.float32)
    flow_spec = jax.ShapeDtypeStruct((batch, height, width, 2), jnp.float32)
    extra_specs = [
        jax.ShapeDtypeStruct((batch, *EXTRA_INPUTS[key][0]), jnp.float32) for key in extra_inputs
    ]
    weight_specs = [jax.ShapeDtypeStruct(weight.shape, weight.dtype) for weight in weights]
    exported = jax.export.export(jax.jit(forward), platforms=platforms)(
        weight_specs, image_spec, image_spec, flow_spec, *extra_specs
    )
    outputs = jax.tree_util.tree_unflatten(exported.out_tree, exported.out_avals)
    metadata = {
        "format": FORMAT,
        "format_version": FORMAT_VERSION,
        **_describe(model, name, height, width, batch_size, outputs, source),
        "platforms": list(platforms),
        "weights": [
            {"name": weight_name, "shape": list(weight.shape), "dtype": str(weight.dtype)}
            for weight_name, weight in zip(weight_names, weights, strict=True)
        ],
        "calling_convention": "Exported.call(weights, image1, image2, flow, *extra): weights "
        "is the list of weights.npz arrays in the order of 'weights', extra the arrays "
        "'extra_inputs' names, in its order; returns a dict of 'outputs'",
    }
    weights_buffer = io.BytesIO()
    np.savez(weights_buffer, **{f"{i:05d}": weight for i, weight in enumerate(weights)})

    def write(path: Path) -> None:
        with zipfile.ZipFile(path, "w", zipfile.ZIP_STORED) as archive:
            archive.writestr(METADATA_MEMBER, json.dumps(metadata, indent=1) + "\n")
            archive.writestr(EXPORTED_MEMBER, bytes(exported.serialize()))
            archive.writestr(WEIGHTS_MEMBER, weights_buffer.getvalue())

    files_lib.write_atomically(output, write)
    return metadata


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
    "batch" unless fixed. The metadata of `export_model` (less the weights) is stored as
    the model's metadata property "gld". The converter is an optional dependency
    (`pip install jax2onnx onnxruntime`).

    The converted graph is run with onnxruntime on random pairs and compared with
    `model.apply`; a difference above `tolerance` (absolute, on any output) refuses the
    export. "vmap" is refused outright: jax2onnx 0.17.1 converted its grouped
    convolution into a graph that runs but is wrong (inverse depth off by 0.1 on a tiny
    model), so every other formulation is preferred for ONNX.

    Args:
      model, variables, output, height, width, batch_size, formulation, source: as
        for `export_model` (the formulation's default is the CPU one).
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
    model, name, output = _checked(
        model, output, height, width, batch_size, formulation, ("cpu",), extra_allowed=False
    )
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
        lambda *inputs: _inference_outputs(model.apply(variables, *inputs)),
        *[jax.ShapeDtypeStruct((1, height, width, c), jnp.float32) for c in (3, 3, 2)],
    )
    names = list(outputs)

    def forward(image1, image2, flow):
        results = _inference_outputs(model.apply(variables, image1, image2, flow))
        return tuple(results[key] for key in names)

    batch = "batch" if batch_size is None else int(batch_size)
    proto = jax2onnx.to_onnx(
        forward,
        [(batch, height, width, 3), (batch, height, width, 3), (batch, height, width, 2)],
        model_name=f"gld_{name}",
        input_names=list(INPUT_NAMES),
        output_names=names,
    )
    check_batch = 2 if batch_size is None else int(batch_size)
    rng = np.random.default_rng(seed)
    inputs = {
        "image1": rng.uniform(-0.5, 0.5, (check_batch, height, width, 3)).astype(np.float32),
        "image2": rng.uniform(-0.5, 0.5, (check_batch, height, width, 3)).astype(np.float32),
        "flow": rng.normal(0.0, 2.0, (check_batch, height, width, 2)).astype(np.float32),
    }
    session = onnxruntime.InferenceSession(
        proto.SerializeToString(), providers=["CPUExecutionProvider"]
    )
    converted = dict(zip(names, session.run(names, inputs), strict=True))
    expected = _inference_outputs(model.apply(variables, *inputs.values()))
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
        **_describe(model, name, height, width, batch_size, outputs, source),
        "onnx_opset": int(proto.opset_import[0].version),
        "jax2onnx_version": importlib.metadata.version("jax2onnx"),
        "onnxruntime_check": {"pairs": check_batch, "tolerance": tolerance},
    }
    entry = proto.metadata_props.add()
    entry.key, entry.value = "gld", json.dumps(metadata)
    files_lib.write_atomically(output, lambda path: onnx.save_model(proto, str(path)))
    return metadata


def export_workdir(
    workdir: str | Path,
    output: str | Path,
    *,
    step: int | None = None,
    platforms: Sequence[str] = ("cpu",),
    batch_size: int | None = None,
    formulation: str | None = None,
    onnx_output: str | Path | None = None,
) -> dict[str, Any]:
    """Exports the latest (or given) checkpoint of a training workdir (`export_model`).

    The image size is the run's training resolution; the run's own formulation (a speed
    choice for the machine it trained on) is replaced by the target platform's. With
    `onnx_output`, the same checkpoint is also converted to ONNX (`export_onnx`), first,
    so that a refused conversion leaves nothing written.

    Returns:
      The metadata written to `output`; with `onnx_output`, plus "onnx": the ONNX
      file's metadata.
    """

    workdir = Path(workdir)
    platforms = check_platforms(platforms)
    config = workdir_lib.load_run_config(workdir)
    # Refused before the checkpoint is read: a bad formulation, or one for a model
    # without per-example filters.
    if "filter_formulation" in registry.full_config(config.model, config.model_config):
        choose_formulation(formulation, platforms, batch_size)
    elif formulation is not None:
        raise ValueError(f"model {config.model!r} has no per-example filters to give a formulation")
    if onnx_output is not None:
        if formulation == "vmap":
            raise ValueError("formulation 'vmap' cannot be exported to ONNX; choose another")
        missing = [
            name for name in ("jax2onnx", "onnxruntime") if not importlib.util.find_spec(name)
        ]
        if missing:
            raise ImportError(f"ONNX export needs {missing}: pip install jax2onnx onnxruntime")
    if config.height < 1 or config.width < 1:
        raise ValueError(
            f"{workdir / 'config.json'} records no training resolution "
            f"(height={config.height}, width={config.width})"
        )
    manager = checkpoint_lib.checkpoint_manager(workdir)
    available = list(manager.all_steps())
    manager.close()
    if not available:
        raise FileNotFoundError(f"no checkpoint in {workdir / 'checkpoints'}")
    if step is not None and step not in available:
        raise ValueError(f"no checkpoint of step {step} in {workdir}; available: {available}")
    step = max(available) if step is None else step
    model, variables, config = workdir_lib.load_trained(workdir, step=step)
    source = {
        "workdir": str(workdir.absolute()),
        "step": int(step),
        "dataset": config.dataset,
        "flow_source": config.flow_source,
    }
    arguments = dict(height=config.height, width=config.width, batch_size=batch_size)
    onnx_metadata = None
    if onnx_output is not None:
        onnx_metadata = export_onnx(
            model, variables, onnx_output, formulation=formulation, source=source, **arguments
        )
    metadata = export_model(
        model,
        variables,
        output,
        platforms=platforms,
        formulation=formulation,
        source=source,
        **arguments,
    )
    return metadata if onnx_metadata is None else {**metadata, "onnx": onnx_metadata}
