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

from gld.inference import export, resampling
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
