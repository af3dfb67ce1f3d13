r"""Exports a trained model to one file that runs with JAX alone (`gld.inference.deploy`).

    python -m experiments.export --workdir=runs/demo --output=runs/demo/model.gldx
    python -m experiments.export --workdir=runs/demo --output=gpu.gldx \
        --platforms=cuda --formulation=vmap --batch_size=1
    python -m experiments.export --workdir=runs/demo --output=both.gldx --platforms=cpu,cuda
    python -m experiments.export --workdir=runs/demo --output=model.gldx --onnx_output=model.onnx

The file (a zip: metadata.json, the `jax.export` module, the weights as .npz) holds the
forward pass at the run's training resolution, with a symbolic batch size unless
--batch_size fixes it. --formulation chooses how the per-example filters are applied
(default: the first platform's, `gld.models.filter_banks.default_formulation`; "vmap" needs
--batch_size). --onnx_output also writes an ONNX model (needs `pip install jax2onnx
onnxruntime`; checked against JAX with onnxruntime before it is written). On the robot:

    from gld.inference.deploy import DeployedModel
    depth = DeployedModel.load("model.gldx")(image1, image2, flow)   # jax + numpy only

A model that reads a given pose or the cameras (trained with --global_source=pose or
flow_pose, or reading a pose against the flow: --pose_refinement_steps, --derotate_flow,
--parallax_depth) takes them after the flow, by keyword (`DeployedModel.extra_inputs`);
a model given the pose that reads it against the flow takes the pose, then the cameras.
The inputs printed after the export say what each is.
"""

from __future__ import annotations

from absl import app, flags

from experiments import common
from gld.inference import workdir_export
from gld.inference.export_interface import PLATFORMS, check_platforms
from gld.models.filter_banks import FORMULATIONS

FLAGS = flags.FLAGS

flags.DEFINE_string("workdir", None, "Training workdir to export.")
flags.DEFINE_string("output", None, "File to write (e.g. runs/demo/model.gldx).")
flags.DEFINE_integer("step", None, "Checkpoint step (default: latest).")
flags.DEFINE_list("platforms", ["cpu"], f"Platforms to lower for, of {', '.join(PLATFORMS)}.")
flags.DEFINE_enum(
    "formulation",
    None,
    list(FORMULATIONS),
    "Per-example filter formulation (default: the first platform's).",
)
flags.DEFINE_integer(
    "batch_size", None, "Fixed batch size (default: any, symbolic).", lower_bound=1
)
flags.DEFINE_string("onnx_output", None, "Also write an ONNX model here (needs jax2onnx).")
flags.DEFINE_string(
    "flow",
    None,
    "The flow the runtime computes: dis, dis_fast, farneback or flow_net:<workdir> (default: "
    "the flow the run's dataset was built with, recorded in <workdir>/dataset_flow.json).",
)
flags.mark_flags_as_required(["workdir", "output"])


def _platforms_are_known(platforms: list[str]) -> bool:
    try:
        check_platforms(platforms)
    except ValueError as error:
        raise flags.ValidationError(str(error)) from error
    return True


flags.register_validator("platforms", _platforms_are_known)


def main(argv: list[str]) -> None:
    if len(argv) > 1:
        raise app.UsageError(f"unexpected arguments: {argv[1:]}")
    common.initialise()
    metadata = workdir_export.export_workdir(
        FLAGS.workdir,
        FLAGS.output,
        step=FLAGS.step,
        platforms=FLAGS.platforms,
        batch_size=FLAGS.batch_size,
        formulation=FLAGS.formulation,
        onnx_output=FLAGS.onnx_output,
        flow=FLAGS.flow,
    )
    batch = metadata["batch_size"] or "any"
    print(
        f"wrote {FLAGS.output}: {metadata['model']} at step {metadata['source']['step']}, "
        f"{metadata['height']}x{metadata['width']} (HxW), batch {batch}, "
        f"platforms {','.join(metadata['platforms'])}, formulation {metadata['formulation']}"
    )
    for entry in metadata["inputs"]:
        print(f"  input  {entry['name']}: {entry['shape']} {entry['dtype']}; {entry['help']}")
    for entry in metadata["outputs"]:
        print(f"  output {entry['name']}: {entry['shape']} {entry['dtype']}")
    print(f"  depth units: {metadata['depth_units']}")
    flow = metadata["flow"]
    print(f"  flow: {', '.join(f'{key} {value}' for key, value in flow.items())}")
    # OpenCV computes a classical flow and the essential matrix's pose of a flow_pose model
    # (`DepthRuntime.needs_opencv`).
    needs_opencv = flow["estimator"] not in ("flow_net", "model") or (
        "flow_rotation" in metadata.get("extra_inputs", ())
    )
    print(
        f"  frames to metric depth: gld.inference.runtime.DepthRuntime.load({FLAGS.output!r})"
        + ("; needs opencv-python-headless" if needs_opencv else "")
    )
    if "onnx" in metadata:
        onnx = metadata["onnx"]
        print(
            f"wrote {FLAGS.onnx_output}: ONNX opset {onnx['onnx_opset']}, formulation "
            f"{onnx['formulation']}, matches JAX within {onnx['onnxruntime_check']['tolerance']}"
        )


if __name__ == "__main__":
    common.run(main)
