"""A training workdir's checkpoint exported: the `jax.export` file and, optionally, ONNX."""

from __future__ import annotations

import importlib.util
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from gld.inference import export, export_interface, onnx_export
from gld.models import registry
from gld.runs import checkpoints as checkpoint_lib
from gld.runs import workdir as workdir_lib


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
    """Exports the latest (or given) checkpoint of a training workdir (`export.export_model`).

    The image size is the run's training resolution; the run's own formulation (a speed
    choice for the machine it trained on) is replaced by the target platform's. With
    `onnx_output`, the same checkpoint is also converted to ONNX
    (`onnx_export.export_onnx`), first, so that a refused conversion leaves nothing written.

    Returns:
      The metadata written to `output`; with `onnx_output`, plus "onnx": the ONNX
      file's metadata.
    """

    workdir = Path(workdir)
    platforms = export_interface.check_platforms(platforms)
    config = workdir_lib.load_run_config(workdir)
    # Refused before the checkpoint is read: a bad formulation, or one for a model
    # without per-example filters.
    if "filter_formulation" in registry.full_config(config.model, config.model_config):
        export_interface.choose_formulation(formulation, platforms, batch_size)
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
        onnx_metadata = onnx_export.export_onnx(
            model, variables, onnx_output, formulation=formulation, source=source, **arguments
        )
    metadata = export.export_model(
        model,
        variables,
        output,
        platforms=platforms,
        formulation=formulation,
        source=source,
        **arguments,
    )
    return metadata if onnx_metadata is None else {**metadata, "onnx": onnx_metadata}
