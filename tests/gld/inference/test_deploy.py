"""Running an exported model (gld/inference/deploy.py) without the training stack; input checks."""

import ast
import json
import sys
import textwrap
import zipfile

import global_local_reference as reference
import numpy as np
import pytest
from conftest import REPO_ROOT, TINY_MODEL, random_variables, run_isolated

from gld.inference import export, onnx_export
from gld.inference.deploy import DeployedModel
from gld.models import registry

HEIGHT, WIDTH = 24, 32
# What a robot need not install: importing any of these in the isolated run fails.
TRAINING_PACKAGES = ("flax", "optax", "orbax", "tensorflow", "tensorflow_datasets", "grain", "cv2")


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    """(model, variables, path) of a tiny untrained global-local model exported for CPU."""
    model = registry.make_model("global_local", **TINY_MODEL)
    variables = random_variables(model, HEIGHT, WIDTH, seed=1)
    path = tmp_path_factory.mktemp("deploy") / "model.gldx"
    export.export_model(model, variables, path, height=HEIGHT, width=WIDTH)
    return model, variables, path


def _pairs(batch_size: int, seed: int):
    rng = np.random.default_rng(seed)
    image1 = rng.integers(0, 256, (batch_size, HEIGHT, WIDTH, 3), dtype=np.uint8)
    image2 = rng.integers(0, 256, (batch_size, HEIGHT, WIDTH, 3), dtype=np.uint8)
    flow = rng.normal(0, 2, (batch_size, HEIGHT, WIDTH, 2)).astype(np.float32)
    return image1, image2, flow


# Run with `python -I` (no PYTHONPATH, user site or working directory on sys.path), so
# the only way in is site-packages, where the training packages are installed; a finder
# placed first on sys.meta_path makes every import of them fail, as on a machine
# without them. The run checks that the finder works and that none got in.
ISOLATED_RUN = textwrap.dedent(
    """
    import importlib.abc, json, sys
    blocked, repo, inputs, outputs = json.loads(sys.argv[1])
    blocked = set(blocked)

    class TrainingStackAbsent(importlib.abc.MetaPathFinder):
        def find_spec(self, name, path=None, target=None):
            if name.partition(".")[0] in blocked:
                raise ModuleNotFoundError(f"No module named {name!r}", name=name)
            return None

    assert not blocked & {name.partition(".")[0] for name in sys.modules}, "imported early"
    sys.meta_path.insert(0, TrainingStackAbsent())
    for name in blocked:
        try:
            __import__(name)
        except ImportError:
            pass
        else:
            raise AssertionError(f"{name} could still be imported")
    sys.path.insert(0, repo)

    import numpy as np
    from gld.inference.deploy import DeployedModel

    model = DeployedModel.load(inputs["model"])
    results = {}
    for batch_size in inputs["batch_sizes"]:
        with np.load(inputs[str(batch_size)]) as pairs:
            predicted = model.predict(pairs["image1"], pairs["image2"], pairs["flow"])
        for key, value in predicted.items():
            results[f"{batch_size}/{key}"] = value
    np.savez(outputs, **results)
    loaded = sorted(name for name in sys.modules if name.partition(".")[0] in blocked)
    assert not loaded, loaded
    gld_modules = sorted(name for name in sys.modules if name.partition(".")[0] == "gld")
    print(json.dumps(gld_modules))
    """
)


def test_runs_without_the_training_stack_and_gives_the_models_outputs(exported, tmp_path):
    model, variables, path = exported
    inputs = {"model": str(path), "batch_sizes": [1, 3]}
    for batch_size in inputs["batch_sizes"]:
        pairs = dict(zip(("image1", "image2", "flow"), _pairs(batch_size, batch_size), strict=True))
        inputs[str(batch_size)] = str(tmp_path / f"pairs{batch_size}.npz")
        np.savez(inputs[str(batch_size)], **pairs)
    outputs = tmp_path / "outputs.npz"
    completed = run_isolated(
        ISOLATED_RUN, *[list(TRAINING_PACKAGES), str(REPO_ROOT), inputs, str(outputs)]
    )
    assert completed.returncode == 0, completed.stderr[-3000:]
    imported = completed.stdout.strip().splitlines()[-1]
    assert imported == '["gld", "gld.inference", "gld.inference.deploy"]'
    # uint8 images are read as value / 255 - 0.5; the network, written out in numpy.
    with np.load(outputs) as results:
        for batch_size in inputs["batch_sizes"]:
            image1, image2, flow = _pairs(batch_size, batch_size)
            expected = reference.global_local(
                model, variables, image1 / 255.0 - 0.5, image2 / 255.0 - 0.5, flow
            )
            for key in ("inv_depth", "depth", "global_params"):
                got = results[f"{batch_size}/{key}"]
                assert got.shape == expected[key].shape
                np.testing.assert_allclose(got, expected[key], rtol=1e-4, atol=1e-6)


def test_deploy_imports_only_jax_numpy_and_the_standard_library():
    tree = ast.parse((REPO_ROOT / "gld" / "inference" / "deploy.py").read_text())
    imported = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            imported |= {alias.name.partition(".")[0] for alias in node.names}
        elif isinstance(node, ast.ImportFrom) and node.level == 0:
            imported.add(node.module.partition(".")[0])
    assert imported - set(sys.stdlib_module_names) == {"jax", "numpy"}


def test_one_pair_uint8_and_float_inputs_agree(exported):
    _, _, path = exported
    deployed = DeployedModel.load(path)
    assert (deployed.height, deployed.width, deployed.batch_size) == (HEIGHT, WIDTH, None)
    assert deployed.metadata["model"] == "global_local"
    image1, image2, flow = _pairs(2, seed=5)
    batch = deployed.predict(image1, image2, flow)
    floats = deployed.predict(image1 / np.float32(255), image2 / np.float32(255), flow)
    np.testing.assert_allclose(floats["depth"], batch["depth"], rtol=1e-6)
    single = deployed(image1[1], image2[1], flow[1])
    assert single.shape == (HEIGHT, WIDTH)
    np.testing.assert_allclose(single, batch["depth"][1], rtol=1e-5)
    np.testing.assert_allclose(batch["depth"], 1.0 / batch["inv_depth"], rtol=1e-5)


def test_bad_inputs_are_named(exported):
    _, _, path = exported
    deployed = DeployedModel.load(path)
    image1, image2, flow = _pairs(2, seed=6)
    with pytest.raises(ValueError, match=r"image1 must be \[B, 24, 32, 3\].*got shape \(2, 20"):
        deployed(image1[:, :20], image2, flow)
    with pytest.raises(ValueError, match=r"flow must be \[B, 24, 32, 2\]"):
        deployed(image1, image2, flow[..., :1])
    with pytest.raises(ValueError, match="image2 must be uint8 or float32, got dtype float64"):
        deployed(image1, image2 / 255.0, flow)
    with pytest.raises(ValueError, match=r"float32 image1 must lie in \[0, 1\]"):
        deployed(image1.astype(np.float32), image2, flow)
    # The former convention, [-0.5, 0.5], is refused rather than misread.
    with pytest.raises(ValueError, match=r"float32 image1 must lie in \[0, 1\]"):
        deployed(image1 / np.float32(255) - np.float32(0.5), image2, flow)
    with pytest.raises(ValueError, match="flow must be float32"):
        deployed(image1, image2, flow.astype(np.float64))
    with pytest.raises(ValueError, match="flow contains NaN"):
        deployed(image1, image2, np.where(flow > 3, np.nan, flow).astype(np.float32))
    with pytest.raises(ValueError, match="same batch size, got 2, 2 and 1"):
        deployed(image1, image2, flow[:1])
    with pytest.raises(ValueError, match="a batch axis or none"):
        deployed(image1[0], image2[0], flow)


def test_bad_files_are_named(exported, tmp_path):
    model, variables, _ = exported
    with pytest.raises(FileNotFoundError, match="nowhere.gldx"):
        DeployedModel.load(tmp_path / "nowhere.gldx")
    (tmp_path / "text.gldx").write_text("not a model")
    with pytest.raises(ValueError, match="text.gldx is not an exported gld model"):
        DeployedModel.load(tmp_path / "text.gldx")
    with zipfile.ZipFile(tmp_path / "partial.gldx", "w") as archive:
        archive.writestr("metadata.json", "{}")
    with pytest.raises(ValueError, match=r"lacks \['model.jaxexport', 'weights.npz'\]"):
        DeployedModel.load(tmp_path / "partial.gldx")
    # A module lowered for GPUs only does not load on this CPU.
    gpu_only = tmp_path / "gpu.gldx"
    export.export_model(model, variables, gpu_only, height=HEIGHT, width=WIDTH, platforms=("cuda",))
    with pytest.raises(ValueError, match=r"exported for \['cuda'\], but JAX runs on 'cpu'"):
        DeployedModel.load(gpu_only)
    # A fixed batch size is enforced with a message saying how to lift it.
    fixed = tmp_path / "fixed.gldx"
    export.export_model(model, variables, fixed, height=HEIGHT, width=WIDTH, batch_size=2)
    with pytest.raises(ValueError, match="exported for batch size 2, got 3"):
        DeployedModel.load(fixed)(*_pairs(3, seed=7))


def test_a_file_of_another_format_or_a_later_version_is_refused(exported, tmp_path):
    _, _, path = exported

    def with_metadata(name, **changes):
        copy = tmp_path / name
        with zipfile.ZipFile(path) as source, zipfile.ZipFile(copy, "w") as target:
            for member in source.namelist():
                data = source.read(member)
                if member == "metadata.json":
                    data = json.dumps({**json.loads(data), **changes})
                target.writestr(member, data)
        return copy

    with pytest.raises(ValueError, match="format 'other' is not"):
        DeployedModel.load(with_metadata("other.gldx", format="other"))
    with pytest.raises(ValueError, match="has format version 4"):
        DeployedModel.load(with_metadata("later.gldx", format_version=4))
    # Versions 1 and 2 read alike, their function given images in [-0.5, 0.5]: this
    # file's function (which subtracts 0.5 itself) so labelled sees image - 1.
    model, variables, _ = exported
    image1, image2, flow = _pairs(1, seed=4)
    for version in (1, 2):
        older = DeployedModel.load(with_metadata(f"v{version}.gldx", format_version=version))
        expected = reference.global_local(
            model, variables, image1 / 255.0 - 1.0, image2 / 255.0 - 1.0, flow
        )
        np.testing.assert_allclose(older(image1, image2, flow), expected["depth"], rtol=1e-4)


def _camera(batch_size: int, focal: float) -> np.ndarray:
    """Normalised intrinsics [B, 4] of a camera of focal length `focal` x the width."""
    return np.tile(np.float32([focal, focal * WIDTH / HEIGHT, 0.5, 0.5]), (batch_size, 1))


@pytest.mark.parametrize(
    "reads",
    [{}, {"derotate_flow": True, "parallax_depth": True}],
    ids=["refinement", "the_main_jobs_derotated_and_triangulated_flow"],
)
def test_a_model_that_refines_its_pose_runs_given_the_cameras(tmp_path, reads):
    """A refinement model (and the main job's, which derotates the flow and triangulates
    it under the refined pose) exports with the cameras as inputs after the flow;
    deployed, it equals the model applied in gld, reads the cameras it is given, and
    names what it lacks."""
    import jax

    model = registry.make_model("global_local", **TINY_MODEL, pose_refinement_steps=2, **reads)
    assert model.extra_inputs == ("intrinsics1", "intrinsics2")
    cameras = dict(intrinsics1=_camera(1, 0.9), intrinsics2=_camera(1, 0.9))
    variables = random_variables(model, HEIGHT, WIDTH, seed=3, **cameras)
    path = tmp_path / "refines.gldx"
    metadata = export.export_model(model, variables, path, height=HEIGHT, width=WIDTH)
    assert metadata["extra_inputs"] == ["intrinsics1", "intrinsics2"]
    assert [entry["name"] for entry in metadata["inputs"]][3:] == ["intrinsics1", "intrinsics2"]
    assert metadata["inputs"][3]["shape"] == ["batch", 4]

    deployed = DeployedModel.load(path)
    assert deployed.extra_inputs == ("intrinsics1", "intrinsics2")
    image1, image2, flow = _pairs(2, seed=8)
    given = dict(intrinsics1=_camera(2, 0.9), intrinsics2=_camera(2, 0.9))
    outputs = deployed.predict(image1, image2, flow, **given)
    as_float = [image / np.float32(255) - np.float32(0.5) for image in (image1, image2)]
    expected = jax.jit(model.apply)(variables, *as_float, flow, **given)
    np.testing.assert_allclose(outputs["depth"], expected["depth"], rtol=1e-4)
    np.testing.assert_allclose(outputs["global_params"], expected["global_params"], atol=1e-5)
    # The cameras reach the refinement: another focal length, another pose and depth.
    other = deployed.predict(
        image1, image2, flow, intrinsics1=_camera(2, 0.4), intrinsics2=_camera(2, 0.4)
    )
    assert not np.allclose(other["global_params"], outputs["global_params"], atol=1e-4)
    # One pair without the batch axis, the cameras as [4].
    single = deployed(
        image1[0],
        image2[0],
        flow[0],
        intrinsics1=given["intrinsics1"][0],
        intrinsics2=given["intrinsics2"][0],
    )
    np.testing.assert_allclose(single, outputs["depth"][0], rtol=1e-4)

    with pytest.raises(
        ValueError, match=r"also reads \['intrinsics1', 'intrinsics2'\].*fx / width"
    ):
        deployed(image1, image2, flow)
    with pytest.raises(ValueError, match=r"intrinsics2 must be \[B, 4\].*got shape \(2, 3\)"):
        deployed(
            image1,
            image2,
            flow,
            intrinsics1=given["intrinsics1"],
            intrinsics2=given["intrinsics2"][:, :3],
        )
    with pytest.raises(ValueError, match="intrinsics1 contains NaN"):
        deployed(
            image1,
            image2,
            flow,
            intrinsics1=given["intrinsics1"] * np.nan,
            intrinsics2=given["intrinsics2"],
        )
    with pytest.raises(ValueError, match=r"does not read \['rotation'\]"):
        deployed(image1, image2, flow, rotation=np.eye(3), **given)
    # ONNX takes the images and flow only, and says so before writing anything.
    onnx_path = tmp_path / "refines.onnx"
    with pytest.raises(ValueError, match="only models of the images and flow convert to ONNX"):
        onnx_export.export_onnx(model, variables, onnx_path, height=HEIGHT, width=WIDTH)
    assert not onnx_path.exists()


def test_a_model_of_the_images_and_flow_refuses_extra_inputs(exported):
    _, _, path = exported
    deployed = DeployedModel.load(path)
    assert deployed.extra_inputs == ()
    with pytest.raises(ValueError, match=r"does not read \['intrinsics1'\]"):
        deployed(*_pairs(1, seed=9), intrinsics1=_camera(1, 0.9))


@pytest.mark.parametrize("global_source", ["pose", "flow_pose"])
def test_a_model_reading_its_given_pose_against_the_flow_runs_given_both(tmp_path, global_source):
    """A model given the pose (odometry, or its flow's essential matrix's) that derotates
    and triangulates the flow under it exports with the pose and then the cameras as
    inputs after the flow; deployed, it equals the model applied in gld, reads both, and
    names what it lacks."""
    import jax

    model = registry.make_model(
        "global_local",
        **TINY_MODEL,
        global_source=global_source,
        derotate_flow=True,
        parallax_depth=True,
    )
    keys = {"pose": ["rotation", "translation"], "flow_pose": ["flow_rotation", "flow_translation"]}
    extra = [*keys[global_source], "intrinsics1", "intrinsics2"]
    assert list(model.extra_inputs) == extra

    def inputs(batch_size, angle, focal):
        rotation = np.eye(3, dtype=np.float32)
        rotation[0, 2], rotation[2, 0] = np.sin(angle), -np.sin(angle)
        rotation[0, 0] = rotation[2, 2] = np.cos(angle)
        translation = np.float32([0.6, 0.0, 0.8])
        values = [
            np.tile(rotation, (batch_size, 1, 1)),
            np.tile(translation, (batch_size, 1)),
            _camera(batch_size, focal),
            _camera(batch_size, focal),
        ]
        return dict(zip(extra, values, strict=True))

    variables = random_variables(model, HEIGHT, WIDTH, seed=4, **inputs(1, 0.0, 0.9))
    path = tmp_path / "given_pose.gldx"
    metadata = export.export_model(model, variables, path, height=HEIGHT, width=WIDTH)
    assert metadata["extra_inputs"] == extra
    assert [entry["name"] for entry in metadata["inputs"]][3:] == extra
    assert [entry["shape"] for entry in metadata["inputs"]][3:] == [
        ["batch", 3, 3],
        ["batch", 3],
        ["batch", 4],
        ["batch", 4],
    ]

    deployed = DeployedModel.load(path)
    assert deployed.extra_inputs == tuple(extra)
    image1, image2, flow = _pairs(2, seed=10)
    given = inputs(2, 0.05, 0.9)
    outputs = deployed.predict(image1, image2, flow, **given)
    as_float = [image / np.float32(255) - np.float32(0.5) for image in (image1, image2)]
    apply = jax.jit(model.apply)
    expected = apply(variables, *as_float, flow, **given)
    np.testing.assert_allclose(outputs["depth"], expected["depth"], rtol=1e-4)
    # Both reach the depth: another focal length, or another rotation, another depth.
    for other in (inputs(2, 0.05, 0.4), inputs(2, -0.05, 0.9)):
        changed = deployed(image1, image2, flow, **other)
        np.testing.assert_allclose(
            changed, apply(variables, *as_float, flow, **other)["depth"], rtol=1e-4
        )
        assert not np.allclose(changed, outputs["depth"], rtol=1e-3)
    # One pair without the batch axis.
    single = deployed(image1[0], image2[0], flow[0], **{k: v[0] for k, v in given.items()})
    np.testing.assert_allclose(single, outputs["depth"][0], rtol=1e-4)

    cameras = {key: given[key] for key in ("intrinsics1", "intrinsics2")}
    pose = {key: given[key] for key in keys[global_source]}
    with pytest.raises(ValueError, match=r"also reads \['intrinsics1', 'intrinsics2'\]"):
        deployed(image1, image2, flow, **pose)
    with pytest.raises(
        ValueError, match=rf"also reads \[{', '.join(map(repr, keys[global_source]))}\]"
    ):
        deployed(image1, image2, flow, **cameras)
    other_pose = "flow_rotation" if global_source == "pose" else "rotation"
    with pytest.raises(ValueError, match=rf"does not read \['{other_pose}'\]"):
        deployed(image1, image2, flow, **given, **{other_pose: given[extra[0]]})
