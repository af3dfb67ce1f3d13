"""The exported runtime (gld/inference/runtime.py): frames of any size to metric depth,
with only the packages of requirements-runtime.txt importable, against DepthPredictor."""

import importlib.metadata
import json
import re
import textwrap

import jax
import numpy as np
import pytest
from conftest import REPO_ROOT, TINY_MODEL, random_variables, run_isolated

from gld import geometry
from gld.inference import export, export_interface, resampling
from gld.inference import inputs as inputs_lib
from gld.inference.predict import DepthPredictor
from gld.inference.runtime import DepthRuntime
from gld.models import registry
from gld.models.flow_net import FlowNet

HEIGHT, WIDTH = 32, 48  # divisible by 16, as the flow network's pyramid needs
FRAME_SIZE = (60, 90)  # frames of another size than the model's, same aspect ratio
CAMERA = (70.0, 70.0, 44.5, 29.5)
SMALL_FLOW_NET = {"feature_channels": (8, 8, 8, 8)}


def _frames(batch_size: int, seed: int, size=FRAME_SIZE) -> tuple[np.ndarray, np.ndarray]:
    """uint8 frame pairs [B, H, W, 3]: a smooth random texture and itself shifted right."""
    rng = np.random.default_rng(seed)
    coarse = rng.integers(0, 256, (batch_size, size[0] // 6 + 2, size[1] // 6 + 2, 3))
    texture = np.repeat(np.repeat(coarse, 6, axis=1), 6, axis=2).astype(np.uint8)
    first = texture[:, : size[0], : size[1]]
    second = texture[:, : size[0], 3 : size[1] + 3]
    return np.ascontiguousarray(first), np.ascontiguousarray(second)


@pytest.fixture(scope="module")
def dis_model(tmp_path_factory):
    """(model, variables, path) of a small encoder-decoder on DIS flow, whose depth varies
    across the image (an untrained global-local model's is nearly constant)."""
    model = registry.make_model("small_encdec")
    variables = random_variables(model, HEIGHT, WIDTH, seed=2)
    path = tmp_path_factory.mktemp("runtime") / "dis.gldx"
    export.export_model(model, variables, path, height=HEIGHT, width=WIDTH)
    return model, variables, path


@pytest.fixture(scope="module")
def flow_net_model(tmp_path_factory):
    """(model, variables, network, network variables, path) of a tiny global-local model
    on a flow network's flow, the network exported in the same file."""
    model = registry.make_model("global_local", **TINY_MODEL)
    variables = random_variables(model, HEIGHT, WIDTH, seed=3)
    network = FlowNet(**SMALL_FLOW_NET)
    images = jax.ShapeDtypeStruct((1, HEIGHT, WIDTH, 3), np.float32)
    shapes = jax.eval_shape(network.init, jax.random.key(0), images, images)
    rng = np.random.default_rng(4)

    def draw(leaf):  # std 1 / sqrt(fan-in), biases 0
        if len(leaf.shape) < 2:
            return np.zeros(leaf.shape, leaf.dtype)
        fan_in = int(np.prod(leaf.shape[:-1]))
        return rng.normal(0.0, fan_in**-0.5, leaf.shape).astype(leaf.dtype)

    network_variables = jax.tree.map(draw, shapes)
    path = tmp_path_factory.mktemp("runtime") / "flow_net.gldx"
    flow = {"estimator": "flow_net", "network": {"architecture": "test"}}
    export.export_model(
        model,
        variables,
        path,
        height=HEIGHT,
        width=WIDTH,
        flow=flow,
        flow_network=(network, network_variables),
    )
    return model, variables, network, network_variables, path


def _moving_frames(size, camera_matrix, rotation, translation):
    """One uint8 pair [H, W, 3]: a smooth random texture, and the view after the relative
    pose (X2 = R X1 + t) of a scene whose depth varies across the image (backward-warped
    by the rigid flow, as its smoothness allows)."""
    import cv2

    first = _frames(1, seed=7, size=size)[0][0]
    first = cv2.GaussianBlur(first, (5, 5), 0)
    grid = geometry.pixel_grid(*size).astype(np.float64)
    depth = 2.0 + 0.02 * grid[..., 0] + 0.5 * np.sin(grid[..., 1] / 7.0)
    flow, _ = geometry.depth_to_flow(depth, camera_matrix, camera_matrix, rotation, translation)
    source = (grid - flow).astype(np.float32)
    second = cv2.remap(
        first, source[..., 0], source[..., 1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT
    )
    return first, second


def _predictor_outputs(model, variables, frames, **measurements):
    predictor = DepthPredictor(model, variables, HEIGHT, WIDTH)
    return predictor.predict(*frames, **measurements)


def test_frames_to_metric_depth_as_the_predictor_gives_it(dis_model):
    model, variables, path = dis_model
    runtime = DepthRuntime.load(path)
    assert runtime.flow["estimator"] == "dis" and runtime.needs_opencv
    frames = _frames(1, seed=0)
    single = (frames[0][0], frames[1][0])
    for measurements in (
        dict(intrinsics=CAMERA, baseline=0.25),
        dict(ranges=[(45.0, 30.0, 1.8), (10.0, 50.0, 2.5)]),
        dict(),
    ):
        got = runtime.predict(*single, **measurements)
        want = _predictor_outputs(model, variables, single, **measurements)
        assert got["depth"].shape == FRAME_SIZE
        # The depth varies: a shift of a pixel or a wrong resize would show.
        assert np.nanstd(want["depth"]) > 0.05 * np.nanmean(want["depth"])
        np.testing.assert_allclose(got["depth"], want["depth"], rtol=1e-5)
        np.testing.assert_allclose(got["inv_depth"], want["inv_depth"], rtol=1e-5)
        np.testing.assert_allclose(got["scale"], want["scale"], rtol=1e-6)
        assert (got["units"], got["scale_source"]) == (want["units"], want["scale_source"])
        if "intrinsics" in measurements:
            np.testing.assert_allclose(got["points"], want["points"], rtol=1e-5, atol=1e-6)
    assert runtime.predict(*single, baseline=0.25)["units"] == "metres"
    assert runtime.predict(*single)["units"] == "baseline"
    # A batch, and float frames in [0, 1], give the same depth as one uint8 pair.
    batch = runtime.predict(*_frames(2, seed=0), baseline=[0.25, 0.5])
    np.testing.assert_allclose(batch["depth"][0], runtime(*single, baseline=0.25), rtol=1e-6)
    floats = runtime(*(frame / np.float32(255) for frame in single), baseline=0.25)
    np.testing.assert_allclose(floats, runtime(*single, baseline=0.25), rtol=1e-5)


def test_frames_of_another_aspect_are_stretched_with_a_warning_or_cropped(dis_model):
    model, variables, path = dis_model
    frames = _frames(1, seed=1, size=(60, 60))
    with pytest.warns(UserWarning, match="stretched"):
        stretched = DepthRuntime.load(path)(frames[0][0], frames[1][0])
    cropped = DepthRuntime.load(path, aspect="crop").predict(frames[0][0], frames[1][0])
    predictor = DepthPredictor(model, variables, HEIGHT, WIDTH, aspect="crop")
    want = predictor.predict(frames[0][0], frames[1][0])
    np.testing.assert_allclose(cropped["depth"], want["depth"], rtol=1e-5)
    # The centred 60x40 crop: NaN above and below it.
    assert np.isnan(cropped["depth"][:10]).all() and np.isfinite(cropped["depth"][10:50]).all()
    assert np.isfinite(stretched).all()


def test_a_wrong_input_is_refused_by_name(dis_model):
    _, _, path = dis_model
    runtime = DepthRuntime.load(path)
    first, second = (frame[0] for frame in _frames(1, seed=2))
    as_float = first / np.float32(255)
    with pytest.raises(ValueError, match=r"float image1 must lie in \[0, 1\]"):
        runtime(as_float - 0.5, second)
    with pytest.raises(ValueError, match=r"float image2 must lie in \[0, 1\]"):
        runtime(first, second * np.float32(1.0))
    with pytest.raises(ValueError, match="image1 has dtype int32"):
        runtime(first.astype(np.int32), second)
    with pytest.raises(ValueError, match="must have the same shape"):
        runtime(first, second[:, :40])
    with pytest.raises(ValueError, match="give baseline= or ranges=, not both"):
        runtime(first, second, baseline=1.0, ranges=[(1, 1, 1.0)])
    with pytest.raises(ValueError, match="baseline must be finite and > 0"):
        runtime(first, second, baseline=-1.0)
    with pytest.raises(ValueError, match=r"reading 0 \(u=200.0.*outside"):
        runtime(first, second, ranges=[(200.0, 10.0, 1.0)])
    with pytest.raises(ValueError, match="rotation= and translation= are for models trained"):
        runtime(first, second, rotation=np.eye(3), translation=[0.1, 0, 0])
    with pytest.raises(ValueError, match="intrinsics must be"):
        runtime(first, second, intrinsics=(1.0, 2.0))


def test_a_model_trained_given_the_pose_takes_the_odometry(tmp_path):
    model = registry.make_model("global_local", **TINY_MODEL, global_source="pose")
    pose = dict(rotation=np.eye(3, dtype=np.float32)[None], translation=np.ones((1, 3), np.float32))
    variables = random_variables(model, HEIGHT, WIDTH, seed=5, **pose)
    path = tmp_path / "pose.gldx"
    export.export_model(model, variables, path, height=HEIGHT, width=WIDTH)
    runtime = DepthRuntime.load(path)
    assert runtime.reads == "odometry"
    frames = tuple(frame[0] for frame in _frames(1, seed=3))
    rotation, translation = np.eye(3), np.array([0.3, 0.0, 0.4])
    got = runtime.predict(*frames, rotation=rotation, translation=translation)
    want = _predictor_outputs(model, variables, frames, rotation=rotation, translation=translation)
    # ||t|| = 0.5 m scales the depth when no other measurement is given.
    assert got["scale_source"] == "baseline" and float(got["scale"]) == pytest.approx(0.5)
    np.testing.assert_allclose(got["depth"], want["depth"], rtol=1e-5)
    with pytest.raises(ValueError, match="give the pair's odometry"):
        runtime(*frames)
    with pytest.raises(ValueError, match="not a rotation matrix"):
        runtime(*frames, rotation=2 * np.eye(3), translation=translation)


@pytest.mark.slow
def test_the_flow_network_in_the_file_gives_the_flow(flow_net_model):
    model, variables, network, network_variables, path = flow_net_model
    runtime = DepthRuntime.load(path)
    assert runtime.flow["estimator"] == "flow_net" and not runtime.needs_opencv
    frames = tuple(frame[0] for frame in _frames(1, seed=4))
    got = runtime.predict(*frames, baseline=0.3)
    want = _flow_net_reference(model, variables, network, network_variables, frames, 0.3)
    assert np.std(want["flow"]) > 0.01
    np.testing.assert_allclose(got["flow"], want["flow"], rtol=1e-4, atol=1e-5)
    np.testing.assert_allclose(got["depth"], want["depth"], rtol=1e-4)


def _flow_net_reference(model, variables, network, network_variables, frames, baseline):
    """The live networks on the frames resized as `DepthPredictor` resizes them."""
    box = (0, 0, *FRAME_SIZE)
    resized = [
        resampling.model_frames(frame[None] / np.float32(255), box, HEIGHT, WIDTH) - 0.5
        for frame in frames
    ]
    flow = network.apply(network_variables, *resized)["flow"]
    inv_depth = model.apply(variables, *resized, flow)["inv_depth"]
    depth = resampling.depth_at_input(np.asarray(inv_depth), box, *FRAME_SIZE)[0]
    return {"flow": np.asarray(flow[0]), "depth": depth * baseline}


# Run with `python -I` and a finder first on sys.meta_path that refuses every installed
# top-level module (of any distribution here) but those of `allowed` (the runtime
# requirements and what they require), as on a robot with only those installed; gld
# comes from the repository.
ISOLATED_RUN = textwrap.dedent(
    """
    import importlib.abc, importlib.metadata, json, sys
    allowed, repo, inputs, outputs = json.loads(sys.argv[1])
    blocked = set(importlib.metadata.packages_distributions()) - set(allowed) - {"gld"}
    # What the interpreter's start-up loaded (site .pth hooks) is there before any check.
    blocked -= {name.partition(".")[0] for name in sys.modules}

    class OnlyTheRuntime(importlib.abc.MetaPathFinder):
        def find_spec(self, name, path=None, target=None):
            if name.partition(".")[0] in blocked:
                raise ModuleNotFoundError(f"No module named {name!r}", name=name)
            return None

    sys.meta_path.insert(0, OnlyTheRuntime())
    for name in ("flax", "optax", "orbax", "grain", "tensorflow_datasets", "absl", "cv2"):
        try:
            __import__(name)
        except ImportError:
            pass
        else:
            assert name not in blocked, f"{name} could still be imported"
    sys.path.insert(0, repo)

    import numpy as np
    from gld.inference.runtime import DepthRuntime

    runtime = DepthRuntime.load(inputs["model"])
    with np.load(inputs["frames"]) as frames:
        result = runtime.predict(frames["image1"], frames["image2"], **inputs["measurements"])
    np.savez(outputs, depth=result["depth"], points=result["points"])
    loaded = sorted({name.partition(".")[0] for name in sys.modules} & blocked)
    assert not loaded, loaded
    print(json.dumps(sorted(name for name in sys.modules if name.startswith("gld"))))
    """
)


def _runtime_modules(with_opencv: bool) -> list[str]:
    """Top-level modules of requirements-runtime.txt's packages and of everything they
    require (installed here), OpenCV's only `with_opencv`."""
    lines = (REPO_ROOT / "requirements-runtime.txt").read_text().splitlines()
    lines = [line.strip() for line in lines if line.strip() and not line.startswith("#")]
    names = [re.match(r"[A-Za-z0-9_.-]+", line).group() for line in lines]
    names = [name for name in names if with_opencv or not name.startswith("opencv")]
    assert {"jax", "numpy", "flatbuffers"} <= set(names)

    def key(name):
        return re.sub(r"[-_.]+", "-", name).lower()

    closure, pending = set(), list(names)
    while pending:
        name = pending.pop()
        if key(name) in closure:
            continue
        closure.add(key(name))
        for requirement in importlib.metadata.distribution(name).requires or []:
            if "extra ==" not in requirement:
                pending.append(re.match(r"[A-Za-z0-9_.-]+", requirement).group())
    provided = importlib.metadata.packages_distributions()
    return sorted(
        module
        for module, distributions in provided.items()
        if any(key(distribution) in closure for distribution in distributions)
    )


def _isolated(path, frames, measurements, with_opencv, tmp_path):
    inputs = {"model": str(path), "frames": str(tmp_path / "frames.npz")}
    inputs["measurements"] = measurements
    np.savez(inputs["frames"], image1=frames[0], image2=frames[1])
    outputs = tmp_path / "outputs.npz"
    allowed = _runtime_modules(with_opencv)
    assert ("cv2" in allowed) == with_opencv and "flax" not in allowed
    completed = run_isolated(ISOLATED_RUN, allowed, str(REPO_ROOT), inputs, str(outputs))
    assert completed.returncode == 0, completed.stderr[-3000:]
    with np.load(outputs) as results:
        return dict(results), json.loads(completed.stdout.strip().splitlines()[-1])


def test_runs_with_only_the_runtime_requirements(dis_model, flow_net_model, tmp_path):
    model, variables, path = dis_model
    frames = tuple(frame[0] for frame in _frames(1, seed=5))
    measurements = dict(intrinsics=list(CAMERA), ranges=[[40.0, 25.0, 2.0]])
    got, modules = _isolated(path, frames, measurements, True, tmp_path)
    want = _predictor_outputs(model, variables, frames, **measurements)
    np.testing.assert_allclose(got["depth"], want["depth"], rtol=1e-5)
    np.testing.assert_allclose(got["points"], want["points"], rtol=1e-5, atol=1e-6)
    assert "gld.inference.predict" not in modules and "gld.models" not in modules

    # A model on a flow network's flow runs with JAX alone: OpenCV cannot be imported.
    model, variables, network, network_variables, path = flow_net_model
    measurements = dict(intrinsics=list(CAMERA), baseline=0.3)
    got, _ = _isolated(path, frames, measurements, False, tmp_path)
    want = _flow_net_reference(model, variables, network, network_variables, frames, 0.3)
    np.testing.assert_allclose(got["depth"], want["depth"], rtol=1e-4)


@pytest.mark.parametrize("global_source", ["pose", "flow_pose"])
def test_a_model_reading_its_given_pose_against_the_flow_takes_the_pose_and_camera(
    tmp_path, global_source
):
    """An exported model given the pose (the odometry, or its flow's essential matrix's)
    that derotates and triangulates the flow under it: the runtime gives it the pose and
    the normalised intrinsics of the camera resized to its resolution, as applying the
    model by hand does, and names what a call lacks in one line."""
    from gld import flow_pose
    from gld.models import global_local as model_lib

    model = registry.make_model(
        "global_local",
        **TINY_MODEL,
        global_source=global_source,
        derotate_flow=True,
        parallax_depth=True,
    )
    given = model_lib.GIVEN_POSE_INPUTS[global_source]
    assert model.extra_inputs == (*given, "intrinsics1", "intrinsics2")
    shapes = {key: (1, *export_interface.EXTRA_INPUTS[key][0]) for key in model.extra_inputs}
    inputs = {key: np.ones(shape, np.float32) for key, shape in shapes.items()}
    variables = random_variables(model, HEIGHT, WIDTH, seed=6, **inputs)
    path = tmp_path / f"{global_source}.gldx"
    export.export_model(model, variables, path, height=HEIGHT, width=WIDTH)
    runtime = DepthRuntime.load(path)
    assert runtime.model.extra_inputs == model.extra_inputs
    assert runtime.needs_camera and runtime.needs_odometry == (global_source == "pose")
    assert runtime.reads == ("odometry and camera" if global_source == "pose" else "camera")
    assert runtime.needs_opencv

    # Frames at twice the model's size, the second the first seen after the odometry's
    # motion over a scene of varying depth; their camera halved keeps its normalised
    # intrinsics (fx / W, fy / H, (cx + 0.5) / W, (cy + 0.5) / H).
    size = (2 * HEIGHT, 2 * WIDTH)
    camera = (80.0, 84.0, 47.5, 31.5)
    normalised = np.float32([80.0 / size[1], 84.0 / size[0], 48.0 / size[1], 32.0 / size[0]])
    rotation = geometry.rotation_matrix(np.array([0.01, -0.02, 0.005]))
    translation = np.array([0.3, 0.0, 0.4])
    frames = _moving_frames(size, inputs_lib.camera_matrix_from(camera), rotation, translation)
    odometry = dict(rotation=rotation, translation=translation) if global_source == "pose" else {}
    got = runtime.predict(*frames, intrinsics=camera, **odometry)

    images = [
        (frame / 255.0).reshape(HEIGHT, 2, WIDTH, 2, 3).mean(axis=(1, 3))[None] - 0.5
        for frame in frames
    ]
    images = [image.astype(np.float32) for image in images]
    flow = got["flow"][None]  # the runtime's DIS flow at the model's size
    if global_source == "pose":
        pose = dict(rotation=rotation[None], translation=translation[None] / 0.5)
    else:
        flow_rotation, flow_translation, found = flow_pose.pose_of_example(
            flow[0], normalised, normalised
        )
        assert found
        pose = dict(flow_rotation=flow_rotation[None], flow_translation=flow_translation[None])
    pose = {key: np.asarray(value, np.float32) for key, value in pose.items()}

    def by_hand(cameras, pose=pose):
        cameras = np.asarray(cameras, np.float32)[None]
        outputs = model.apply(
            variables, *images, flow, **pose, intrinsics1=cameras, intrinsics2=cameras
        )
        return np.asarray(outputs["inv_depth"][0])

    expected = by_hand(normalised)
    np.testing.assert_allclose(got["inv_depth"], expected, rtol=1e-4, atol=1e-6)
    # The camera and the pose reach the depth: the camera normalised at the model's size
    # without the resize, or the pose transposed, give another.
    assert not np.allclose(by_hand(2 * normalised), expected, rtol=1e-3)
    transposed = {
        key: np.swapaxes(value, 1, 2) if value.ndim == 3 else value for key, value in pose.items()
    }
    assert not np.allclose(by_hand(normalised, transposed), expected, rtol=1e-3)
    if global_source == "pose":
        assert got["scale_source"] == "baseline" and float(got["scale"]) == pytest.approx(0.5)

    messages = []
    with pytest.raises(ValueError, match="give intrinsics=") as refused:
        runtime(*frames, **odometry)
    messages.append(str(refused.value))
    if global_source == "pose":
        with pytest.raises(ValueError, match="give the pair's odometry") as refused:
            runtime(*frames, intrinsics=camera)
    else:
        with pytest.raises(ValueError, match="rotation= and translation= are for") as refused:
            runtime(*frames, intrinsics=camera, rotation=rotation, translation=translation)
    messages.append(str(refused.value))
    assert all("\n" not in message for message in messages)


@pytest.mark.parametrize(
    "extra_inputs",
    [
        ("rotation",),
        ("rotation", "translation", "flow_rotation", "flow_translation"),
        ("flow_rotation", "flow_translation", "intrinsics1", "intrinsics2", "depth"),
    ],
    ids=["half_a_pose", "two_poses", "an_unknown_key"],
)
def test_a_file_reading_what_the_runtime_cannot_give_is_refused(extra_inputs):
    import types

    model = types.SimpleNamespace(
        flow={"estimator": "model"},
        height=HEIGHT,
        width=WIDTH,
        flow_network=None,
        metadata={},
        extra_inputs=extra_inputs,
    )
    with pytest.raises(ValueError, match="which this runtime cannot give"):
        DepthRuntime(model)
