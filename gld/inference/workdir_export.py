"""A training workdir's checkpoint exported: the `jax.export` file and, optionally, ONNX.

The file records how the runtime computes the model's input flow: the flow its dataset
was built with, which `experiments.train` writes to `<workdir>/dataset_flow.json`
(`FLOW_RECORD`), or the estimator given (`flow=`). A flow network's flow exports that
network into the same file, checked to be the one the dataset was built with.
"""

from __future__ import annotations

import importlib.util
import json
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from gld import flow as flow_lib
from gld.arguments import ArgumentError
from gld.inference import export, export_interface, onnx_export
from gld.models import registry
from gld.runs import checkpoints as checkpoint_lib
from gld.runs import trained_flow
from gld.runs import workdir as workdir_lib

# The dataset's flow estimator ("flow_estimator_source" of its card), as the run trained on it.
FLOW_RECORD = "dataset_flow.json"


def run_flow(workdir: Path, model_name: str, flow: str | None) -> tuple[dict | None, Any]:
    """(the export's "flow" or None for a model with its own, (FlowNet, variables) of a
    flow network's flow or None).

    Args:
      workdir: the training run.
      model_name: its model (`gld.models.registry.MODELS`).
      flow: a `gld.flow` estimator name or "flow_net:<workdir>"; None: the run's record.
    """
    if export_interface.estimates_own_flow(registry.MODELS[model_name]):
        if flow is not None:
            raise ArgumentError(f"model {model_name!r} estimates its own flow: give no flow")
        return None, None
    recorded = {}
    if flow is None:
        path = workdir / FLOW_RECORD
        if not path.is_file():
            raise ArgumentError(
                f"{workdir} does not record which flow its dataset was built with ({FLOW_RECORD} "
                "is written by experiments.train): give it, --flow=dis (every dataset's "
                "default) or the dataset's --flow_estimator"
            )
        recorded = json.loads(path.read_text())
        flow = recorded["estimator"]
    try:
        flow_lib.check_estimator(flow)
    except ValueError as error:
        raise ArgumentError(str(error)) from None
    if not flow_lib.is_learned(flow):
        return flow_lib.runtime_settings(flow), None
    network = trained_flow.TrainedFlowNet(
        Path(flow[len(flow_lib.LEARNED_PREFIX) :]).expanduser(), step=recorded.get("step")
    )
    described = network.describe()
    if recorded.get("params_sha256", described["params_sha256"]) != described["params_sha256"]:
        raise ArgumentError(
            f"the flow network {flow} (step {described['step']}) is not the one {workdir}'s "
            f"dataset was built with (parameters sha256 {recorded['params_sha256'][:12]}, "
            f"now {described['params_sha256'][:12]})"
        )
    return {"estimator": "flow_net", "network": described}, (network.model, network.variables)


def export_workdir(
    workdir: str | Path,
    output: str | Path,
    *,
    step: int | None = None,
    platforms: Sequence[str] = ("cpu",),
    batch_size: int | None = None,
    formulation: str | None = None,
    onnx_output: str | Path | None = None,
    flow: str | None = None,
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
    has_filters = "filter_formulation" in registry.full_config(config.model, config.model_config)
    try:
        if has_filters:
            export_interface.choose_formulation(formulation, platforms, batch_size)
        elif formulation is not None:
            raise ValueError(
                f"model {config.model!r} has no per-example filters to give a formulation"
            )
        if onnx_output is not None and formulation == "vmap":
            raise ValueError("formulation 'vmap' cannot be exported to ONNX; choose another")
    except ValueError as error:
        raise ArgumentError(f"--formulation={formulation}: {error}") from None
    if onnx_output is not None:
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
    try:
        step = checkpoint_lib.checkpointed_steps(manager, step)[0]
    finally:
        manager.close()
    flow_entry, flow_network = run_flow(workdir, config.model, flow)
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
        flow=flow_entry,
        flow_network=flow_network,
        **arguments,
    )
    return metadata if onnx_metadata is None else {**metadata, "onnx": onnx_metadata}
