"""DepthPredictor and batch prediction over a recording (gld/inference/predict.py): sizes, channels,
dtypes, metric scale, intrinsics, clear errors, and the files a recording's run writes."""

import warnings

import cv2
import global_local_reference as reference
import jax
import numpy as np
import pytest
from conftest import TINY_MODEL

from gld import flow as flow_lib
from gld.inference import depth_io, inputs, recordings
from gld.inference import frames as frames_lib
from gld.inference.predict import DepthPredictor
from gld.models import global_local as model_lib
from gld.models import registry
from gld.runs import state as state_lib

HEIGHT, WIDTH = 48, 64


@pytest.fixture(scope="module")
def tiny_predictor():
    """An untrained tiny global-local model at 64x48: fast, deterministic, positive depth."""
    model = registry.make_model("global_local", **TINY_MODEL)
    # Seeded small weights of the initial variables' shapes: compiling Flax's
    # initialisers costs seconds of CPU that these tests do not need.
    shapes = jax.eval_shape(lambda: state_lib.init_variables(model, HEIGHT, WIDTH, 0))
    rng = np.random.default_rng(0)
    variables = jax.tree_util.tree_map(
        lambda leaf: (0.1 * rng.standard_normal(leaf.shape)).astype(leaf.dtype), shapes
    )
    return DepthPredictor(model, variables, HEIGHT, WIDTH)


def _pair(height=HEIGHT, width=WIDTH, seed=0):
    rng = np.random.default_rng(seed)
    image1 = cv2.GaussianBlur(rng.integers(0, 256, (height, width, 3), dtype=np.uint8), (5, 5), 0)
    return image1, np.roll(image1, 2, axis=1)


def _resize_weights(out_size, in_size, kind):
    """[out, in] weights of a 1-D resize, pixel centres at integer coordinates.

    "area": output pixel i averages the input over [i, i + 1) * in / out, each input
    pixel weighted by its overlap. "linear": output pixel i interpolates the input at
    (i + 0.5) * in / out - 0.5, clamped to the image.
    """
    scale = in_size / out_size
    weights = np.zeros((out_size, in_size))
    for i in range(out_size):
        if kind == "area":
            for j in range(in_size):
                overlap = min(j + 1, (i + 1) * scale) - max(j, i * scale)
                weights[i, j] = max(overlap, 0.0) / scale
        else:
            source = min(max((i + 0.5) * scale - 0.5, 0.0), in_size - 1)
            low = int(np.floor(source))
            high = min(low + 1, in_size - 1)
            weights[i, low] += 1.0 - (source - low)
            weights[i, high] += source - low
    return weights


def _resized(images, height, width, kind):
    """[B, H, W, C] -> [B, height, width, C], separable weights of `_resize_weights`."""
    rows = _resize_weights(height, images.shape[1], kind)
    cols = _resize_weights(width, images.shape[2], kind)
    return np.einsum("ih,bhwc,jw->bijc", rows, np.asarray(images, np.float64), cols)


def _model_by_hand(predictor, image1, image2, flow):
    """The model's outputs on a batch at any size, the documented way: images to [0, 1],
    area-resized to the model's size, shifted to [-0.5, 0.5]; the flow area-resized and
    each component scaled as its axis (pixels of the model's image); the network written
    out in numpy."""
    _, in_height, in_width, _ = flow.shape
    images = [_resized(image / 255.0, HEIGHT, WIDTH, "area") - 0.5 for image in (image1, image2)]
    model_flow = _resized(flow, HEIGHT, WIDTH, "area") * [WIDTH / in_width, HEIGHT / in_height]
    return reference.global_local(predictor.model, predictor.variables, *images, model_flow)


def test_prediction_is_the_documented_pipeline_written_out_by_hand(tiny_predictor):
    # Pairs at 1.5 times the model's size. The model's inverse depth is resized
    # bilinearly to the input and inverted, then times the baseline.
    in_height, in_width = 3 * HEIGHT // 2, 3 * WIDTH // 2
    rng = np.random.default_rng(3)
    image1 = rng.integers(0, 256, (2, in_height, in_width, 3), dtype=np.uint8)
    image2 = rng.integers(0, 256, (2, in_height, in_width, 3), dtype=np.uint8)
    flow = rng.normal(0.0, 4.0, (2, in_height, in_width, 2)).astype(np.float32)
    outputs = tiny_predictor.predict(image1, image2, flow=flow, baseline=[0.3, 2.0])
    expected = _model_by_hand(tiny_predictor, image1, image2, flow)
    np.testing.assert_allclose(
        outputs["global_params"], expected["global_params"], rtol=1e-4, atol=1e-6
    )
    np.testing.assert_allclose(outputs["inv_depth"], expected["inv_depth"], rtol=1e-4)
    inv_depth = _resized(expected["inv_depth"][..., None], in_height, in_width, "linear")
    depth = 1.0 / inv_depth[..., 0]
    np.testing.assert_allclose(outputs["depth_baseline_units"], depth, rtol=1e-4)
    np.testing.assert_allclose(outputs["depth"][0], 0.3 * depth[0], rtol=1e-4)
    np.testing.assert_allclose(outputs["depth"][1], 2.0 * depth[1], rtol=1e-4)

    # Another aspect ratio, stretched to the model's: x shrinks by 2/3, y not at all.
    pair = (image1[:1, :HEIGHT], image2[:1, :HEIGHT], flow[:1, :HEIGHT])
    with pytest.warns(UserWarning, match="stretched"):
        stretched = tiny_predictor.predict(*pair)
    expected = _model_by_hand(tiny_predictor, *pair)
    np.testing.assert_allclose(stretched["inv_depth"], expected["inv_depth"], rtol=1e-4)

    # Without flow=, the flow is estimated (DIS) on the resized images, in their pixels.
    resized = [
        cv2.resize(image.astype(np.float32) / 255.0, (WIDTH, HEIGHT), interpolation=cv2.INTER_AREA)
        for image in (image1[0], image2[0])
    ]
    expected = reference.global_local(
        tiny_predictor.model,
        tiny_predictor.variables,
        resized[0][None] - 0.5,
        resized[1][None] - 0.5,
        flow_lib.estimate(*resized, "dis")[None],
    )
    estimated = tiny_predictor.predict(image1[0], image2[0])
    np.testing.assert_allclose(estimated["inv_depth"], expected["inv_depth"][0], rtol=1e-4)


def test_predictor_accepts_any_size_and_dtype_and_returns_input_size(tiny_predictor):
    rng = np.random.default_rng(0)
    image1 = rng.integers(0, 256, (60, 80, 3), dtype=np.uint8)
    image2 = np.roll(image1, 2, axis=1)
    outputs = tiny_predictor.predict(image1, image2)
    depth = outputs["depth"]
    assert depth.shape == (60, 80) and np.all(depth > 0) and np.all(np.isfinite(depth))
    assert outputs["units"] == "baseline" and outputs["scale_source"] == "none"
    # float images in [0, 1] give the same answer as the uint8 ones
    np.testing.assert_allclose(tiny_predictor(image1 / 255.0, image2 / 255.0), depth, rtol=1e-4)


def test_baseline_and_ranges_give_metric_depth(tiny_predictor):
    image1, image2 = _pair()
    plain = tiny_predictor.predict(image1, image2)
    assert plain["units"] == "baseline" and float(plain["scale"]) == 1.0
    by_baseline = tiny_predictor.predict(image1, image2, baseline=0.3)
    assert by_baseline["units"] == "metres" and by_baseline["scale_source"] == "baseline"
    np.testing.assert_allclose(by_baseline["depth"], 0.3 * plain["depth"], rtol=1e-6)
    np.testing.assert_allclose(by_baseline["depth_baseline_units"], plain["depth"])
    # One reading: the metric map passes through it exactly.
    by_range = tiny_predictor.predict(image1, image2, ranges=[(10, 20, 2.5)])
    assert by_range["scale_source"] == "ranges"
    np.testing.assert_allclose(by_range["depth"][20, 10], 2.5, rtol=1e-5)
    np.testing.assert_allclose(by_range["scale"], 2.5 / plain["depth"][20, 10], rtol=1e-5)
    # __call__ takes the same measurements.
    np.testing.assert_allclose(
        tiny_predictor(image1, image2, baseline=0.3), by_baseline["depth"], rtol=1e-6
    )


def test_batches_take_one_measurement_per_pair(tiny_predictor):
    pairs = [_pair(seed=seed) for seed in range(2)]
    images1 = np.stack([first for first, _ in pairs])
    images2 = np.stack([second for _, second in pairs])
    plain = tiny_predictor.predict(images1, images2)["depth"]
    scaled = tiny_predictor(images1, images2, baseline=[0.5, 2.0])
    np.testing.assert_allclose(scaled, plain * np.array([0.5, 2.0])[:, None, None], rtol=1e-6)
    readings = [np.array([[3.0, 4.0, 1.0]]), np.array([[5.0, 6.0, 2.0], [7.0, 8.0, 2.0]])]
    ranged = tiny_predictor.predict(images1, images2, ranges=readings)
    assert ranged["scale"].shape == (2,)
    np.testing.assert_allclose(ranged["depth"][0, 4, 3], 1.0, rtol=1e-5)
    with pytest.raises(ValueError, match=r"ranges\[1\]: reading 0 .*outside the 64x48"):
        tiny_predictor(images1, images2, ranges=[readings[0], [(64.0, 1.0, 1.0)]])
    with pytest.raises(ValueError, match="one per pair"):
        tiny_predictor(images1, images2, baseline=[0.5, 1.0, 2.0])
    with pytest.raises(ValueError, match="one .* per pair"):
        tiny_predictor(images1, images2, ranges=readings[:1])


def test_bad_measurements_are_refused(tiny_predictor):
    image1, image2 = _pair()
    with pytest.raises(ValueError, match="baseline must be finite and > 0"):
        tiny_predictor(image1, image2, baseline=0.0)
    with pytest.raises(ValueError, match="not both"):
        tiny_predictor(image1, image2, baseline=1.0, ranges=[(1, 1, 1.0)])
    with pytest.raises(ValueError, match=r"ranges: reading 0 .*distance must be > 0"):
        tiny_predictor(image1, image2, ranges=[(1, 1, -1.0)])
    with pytest.raises(ValueError, match=r"ranges must be .*\[N, 3\]"):
        tiny_predictor(image1, image2, ranges=[(1, 1)])


def test_greyscale_is_replicated_and_alpha_dropped(tiny_predictor):
    image1, image2 = _pair()
    grey1, grey2 = image1[..., 0], image2[..., 0]
    replicated = tiny_predictor(
        np.repeat(grey1[..., None], 3, -1), np.repeat(grey2[..., None], 3, -1)
    )
    np.testing.assert_allclose(tiny_predictor(grey1, grey2), replicated, rtol=1e-6)
    np.testing.assert_allclose(
        tiny_predictor(grey1[..., None], grey2[..., None]), replicated, rtol=1e-6
    )
    alpha = np.random.default_rng(1).integers(0, 256, (HEIGHT, WIDTH, 1), dtype=np.uint8)
    rgba1, rgba2 = np.concatenate([image1, alpha], -1), np.concatenate([image2, alpha], -1)
    np.testing.assert_allclose(
        tiny_predictor(rgba1, rgba2), tiny_predictor(image1, image2), rtol=1e-6
    )
    with pytest.raises(ValueError, match="image1 has 1 channel.*image2 3"):
        tiny_predictor(grey1, image2)


@pytest.mark.parametrize(
    "image, message",
    [
        (np.zeros((20, 30, 3), np.uint16), "image1 has dtype uint16"),
        (np.zeros((20, 30, 3), np.int32), "image1 has dtype int32"),
        (np.zeros((20, 30, 3), bool), "image1 has dtype bool"),
        (np.zeros((20, 30, 3), np.float32) + 7.0, r"\[0, 1\]"),
        (np.full((20, 30, 3), np.nan, np.float32), "NaN"),
        (np.zeros((0, 0, 3), np.uint8), r"image1 is empty: 0x0"),
        (np.zeros((0, 20, 30, 3), np.uint8), "image1 is an empty batch"),
        (np.zeros((2, 20, 30), np.uint8), r"channel axis: \[B, H, W, 1\]"),
        (np.zeros((20, 30, 2), np.uint8), "C in"),
        (np.zeros((20,), np.uint8), "image1 must be"),
    ],
)
def test_inputs_outside_the_rules_are_refused_by_name(tiny_predictor, image, message):
    with pytest.raises(ValueError, match=message):
        tiny_predictor(image, image)


def test_flow_must_match_and_be_finite(tiny_predictor):
    image1, image2 = _pair()
    with pytest.raises(ValueError, match="image2.*shape"):
        tiny_predictor(image1, image2[:, :-1])
    with pytest.raises(ValueError, match="flow must be"):
        tiny_predictor(image1, image2, flow=np.zeros((HEIGHT, WIDTH, 3), np.float32))
    flow = np.zeros((HEIGHT, WIDTH, 2), np.float32)
    flow[3, 4, 0] = np.nan
    flow[5, 6, 1] = np.inf
    with pytest.raises(ValueError, match="flow contains 2 NaN or inf"):
        tiny_predictor(image1, image2, flow=flow)


def test_another_aspect_ratio_warns_when_stretched_and_crops_on_request(tiny_predictor):
    image1, image2 = _pair(48, 96)  # 2:1 against the model's 4:3
    with pytest.warns(UserWarning, match=r"input 96x48 .*stretched"):
        stretched = tiny_predictor(image1, image2)
    assert stretched.shape == (48, 96) and np.all(np.isfinite(stretched))
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # same aspect at twice the size: no warning
        tiny_predictor(*_pair(96, 128))
    cropping = DepthPredictor(
        tiny_predictor.model, tiny_predictor.variables, HEIGHT, WIDTH, aspect="crop"
    )
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        cropped = cropping(image1, image2)
    # The centred 64x48 crop of a 96x48 image: columns 16..79 hold depth, the rest NaN.
    assert np.all(np.isnan(cropped[:, :16])) and np.all(np.isnan(cropped[:, 80:]))
    np.testing.assert_allclose(
        cropped[:, 16:80], tiny_predictor(image1[:, 16:80], image2[:, 16:80]), rtol=1e-6
    )
    with pytest.raises(ValueError, match="aspect must be one of"):
        DepthPredictor(tiny_predictor.model, tiny_predictor.variables, 4, 4, aspect="pad")


def test_intrinsics_give_points_and_the_model_camera(tiny_predictor):
    image1, image2 = _pair(96, 128)
    fx, fy, cx, cy = 100.0, 110.0, 60.0, 50.0
    outputs = tiny_predictor.predict(image1, image2, baseline=2.0, intrinsics=(fx, fy, cx, cy))
    points, depth = outputs["points"], outputs["depth"]
    assert points.shape == (96, 128, 3)
    np.testing.assert_allclose(points[..., 2], depth, rtol=1e-6)
    np.testing.assert_allclose(
        points[7, 30], np.array([(30 - cx) / fx, (7 - cy) / fy, 1.0]) * depth[7, 30], 1e-5
    )
    # The model saw the image at half the size: f halves, pixel centres map u -> (u+0.5)/2-0.5.
    np.testing.assert_allclose(
        outputs["model_camera_matrix"],
        [[fx / 2, 0, (cx + 0.5) / 2 - 0.5], [0, fy / 2, (cy + 0.5) / 2 - 0.5], [0, 0, 1]],
    )
    with pytest.raises(ValueError, match="fx, fy > 0"):
        tiny_predictor.predict(image1, image2, intrinsics=(0.0, 1.0, 2.0, 3.0))
    with pytest.raises(ValueError, match="intrinsics must be"):
        tiny_predictor.predict(image1, image2, intrinsics=(1.0, 2.0, 3.0))


def test_resized_camera_projects_a_point_where_the_resized_image_shows_it():
    camera = np.array([[300.0, 0, 310.0], [0, 290.0, 250.0], [0, 0, 1]])
    point = np.array([0.4, -0.3, 2.0])
    pixel = (camera @ point)[:2] / point[2]
    box = inputs.crop_box(480, 800, 48, 64, "crop")  # top, left, 480, 640
    assert box == (0, 80, 480, 640)
    resized = inputs.resize_camera_matrix(camera, box, 48, 64)
    expected = (pixel - [box[1], box[0]] + 0.5) * [64 / 640, 48 / 480] - 0.5
    np.testing.assert_allclose((resized @ point)[:2] / point[2], expected, rtol=1e-9)


# ----------------------------------------------------------------- recordings


def test_range_readings_follow_the_converters_csv(tmp_path):
    names = ["1305.10", "1305.20", "1305.30"]
    path = tmp_path / "range.csv"
    path.write_text(
        "frame,u,v,depth\n# a comment\n1305.10,3,4,1.5\n1305.10,5.5,6,2.5\n2,1,1,0.75\n"
        "1305.20,1,1,0\n1305.20,1,1,nan\n"
    )
    readings = recordings.read_range_readings(path, names, (10, 12), depth_scale=2.0)
    assert sorted(readings) == [0, 2]  # frame 1's readings have no return
    np.testing.assert_allclose(readings[0], [[3, 4, 3.0], [5.5, 6, 5.0]])
    np.testing.assert_allclose(readings[2], [[1, 1, 1.5]])
    path.write_text("frame,u,v,depth\n1305.10,12,4,1.5\n")
    with pytest.raises(ValueError, match=r"range.csv:2: pixel \(12.0, 4.0\) outside the 12x10"):
        recordings.read_range_readings(path, names, (10, 12))
    path.write_text("1305.10,1,4,1.5\nnope,1,1,1\n")
    with pytest.raises(ValueError, match=r"range.csv:2: frame 'nope' is not a frame"):
        recordings.read_range_readings(path, names, (10, 12))
    path.write_text("1305.10,1,4\n")
    with pytest.raises(ValueError, match="range.csv:1: expected frame,u,v,depth"):
        recordings.read_range_readings(path, names, (10, 12))
    with pytest.raises(FileNotFoundError, match="missing.csv"):
        recordings.read_range_readings(tmp_path / "missing.csv", names, (10, 12))


def test_pairs_by_gap_or_file_and_the_plan_skips_pairs_without_a_measurement(tmp_path):
    assert recordings.frame_pairs(4, 2) == [(0, 2), (1, 3)]
    with pytest.raises(ValueError, match="make no pair"):
        recordings.frame_pairs(2, 2)
    path = tmp_path / "pairs.txt"
    path.write_text("# frame1 frame2\na c\n1, 3\n")
    assert recordings.read_pairs_file(path, ["a", "b", "c", "d"]) == [(0, 2), (1, 3)]
    path.write_text("a e\n")
    with pytest.raises(ValueError, match="pairs.txt:1: frame 'e' is not a frame"):
        recordings.read_pairs_file(path, ["a", "b"])
    pairs = [(0, 1), (1, 2), (2, 3)]
    plan = recordings.plan_recording(pairs, ranges={0: np.ones((1, 3)), 2: np.ones((2, 3))})
    assert plan.pairs == [(0, 1), (2, 3)] and len(plan.ranges[1]) == 2
    assert plan.skipped == {"no range reading on the first frame": 1}
    positions = np.array([[0, 0, 0], [0, 0, 0], [0.3, 0.4, 0], [0.3, 0.4, 1.0]])
    plan = recordings.plan_recording(pairs, positions=positions)
    assert plan.pairs == [(1, 2), (2, 3)] and plan.baselines == pytest.approx([0.5, 1.0])
    with pytest.raises(ValueError, match="no pair left"):
        recordings.plan_recording(pairs[:1], positions=positions)


def test_video_frames_stream_in_order_and_seek_back(tmp_path):
    path = str(tmp_path / "clip.avi")
    writer = cv2.VideoWriter(path, cv2.VideoWriter_fourcc(*"MJPG"), 10, (32, 24))
    for index in range(7):
        writer.write(np.full((24, 32, 3), 30 * index, np.uint8))
    writer.release()
    frames = frames_lib.VideoFrames(path, cache_size=2)
    assert len(frames) == 7 and frames.names[3] == "000003"
    for index in [0, 3, 1, 6, 2]:  # forward, back out of the cache, forward again
        assert abs(frames.read(index).mean() - 30 * index) < 3
    frames.close()


def test_predict_recording_writes_every_pair_in_batches(tiny_predictor, tmp_path):
    frames_dir = tmp_path / "frames"
    paths = []
    image, _ = _pair(HEIGHT, WIDTH)
    for index in range(4):
        paths.append(frames_dir / f"f{index}.png")
        frames_dir.mkdir(exist_ok=True)
        cv2.imwrite(str(paths[-1]), np.roll(image, 2 * index, axis=1))
    frames = frames_lib.ImageFolderFrames(paths)
    positions = np.array([[0.0, 0, 0], [0.5, 0, 0], [1.5, 0, 0], [1.5, 0, 0]])
    plan = recordings.plan_recording(recordings.frame_pairs(4), positions=positions)
    with pytest.raises(ValueError, match="needs metric depth"):
        recordings.predict_recording(
            tiny_predictor, frames, recordings.plan_recording([(0, 1)]), tmp_path / "out"
        )
    out = tmp_path / "out"
    summary = recordings.predict_recording(
        tiny_predictor, frames, plan, out, batch_size=3, depth_format="npy"
    )
    assert summary["pairs_written"] == 2 and summary["units"] == "metres"
    assert summary["pairs_skipped"] == {"baseline <= 0.0 m": 1}
    assert sorted(p.name for p in (out / "depth").iterdir()) == ["f0__f1.npy", "f1__f2.npy"]
    expected = tiny_predictor(
        cv2.cvtColor(cv2.imread(str(paths[1])), cv2.COLOR_BGR2RGB),
        cv2.cvtColor(cv2.imread(str(paths[2])), cv2.COLOR_BGR2RGB),
        baseline=1.0,
    )
    np.testing.assert_allclose(np.load(out / "depth" / "f1__f2.npy"), expected, rtol=1e-5)
    rows = (out / "pairs.csv").read_text().splitlines()
    assert rows[0].startswith("pair,frame1,frame2,scale") and rows[2].startswith("f1__f2,f1,f2,1,")


def test_predict_recording_refuses_frames_outside_the_rules_before_writing(
    tiny_predictor, tmp_path
):
    frames_dir = tmp_path / "frames"
    frames_dir.mkdir()
    paths = [frames_dir / f"{index}.png" for index in range(2)]
    for path in paths:
        cv2.imwrite(str(path), np.full((HEIGHT, WIDTH, 3), 4000, np.uint16))
    plan = recordings.plan_recording([(0, 1)])
    with pytest.raises(ValueError, match="frame 0 has dtype uint16"):
        recordings.predict_recording(
            tiny_predictor,
            frames_lib.ImageFolderFrames(paths),
            plan,
            tmp_path / "out",
            depth_format="npy",
        )
    assert not (tmp_path / "out").exists()


def test_depth_files_round_trip(tmp_path):
    depth = np.array([[1.2344, np.nan], [-1.0, 70.0]], np.float32)
    unstored = depth_io.write_depth_png(tmp_path / "d.png", depth)
    from gld.evaluation import stored_predictions

    stored = stored_predictions.load_depth(tmp_path / "d.png")
    np.testing.assert_allclose(stored, [[1.234, 0.0], [0.0, 0.0]], atol=1e-6)
    assert unstored == 3  # NaN, negative, beyond 65.535 m
    points = np.array([[0.1, 0.2, 1.5], [-0.3, 0.0, 2.0]], np.float32)
    colours = np.array([[255, 0, 10], [1, 2, 3]], np.uint8)
    depth_io.write_ply(tmp_path / "p.ply", points, colours)
    loaded = depth_io.read_ply(tmp_path / "p.ply")
    np.testing.assert_array_equal(loaded["points"], points)
    np.testing.assert_array_equal(loaded["colours"], colours)


def _given_pose_predictor(global_source, **options):
    model = registry.make_model(
        "global_local", **{**TINY_MODEL, "global_source": global_source, **options}
    )
    shapes = jax.eval_shape(lambda: state_lib.init_variables(model, HEIGHT, WIDTH, 0))
    rng = np.random.default_rng(1)
    variables = jax.tree_util.tree_map(
        lambda leaf: (0.1 * rng.standard_normal(leaf.shape)).astype(leaf.dtype), shapes
    )
    return DepthPredictor(model, variables, HEIGHT, WIDTH)


def test_odometry_reaches_the_model_as_the_pose_it_was_trained_given():
    from gld import geometry

    predictor = _given_pose_predictor("pose")
    assert predictor.given_pose == "pose"
    # Two camera-to-world poses (a TUM trajectory's), the second moved and turned.
    camera_to_world1 = np.eye(4)
    camera_to_world1[:3, :3] = geometry.rotation_matrix(np.array([0.1, -0.2, 0.05]))
    camera_to_world1[:3, 3] = [1.0, 2.0, 0.5]
    camera_to_world2 = np.eye(4)
    camera_to_world2[:3, :3] = geometry.rotation_matrix(np.array([0.12, -0.15, 0.02]))
    camera_to_world2[:3, 3] = [1.3, 2.1, 0.4]
    rotation, translation = recordings.relative_motion(camera_to_world1, camera_to_world2)
    # The training convention: a world point in camera 1's frame maps to camera 2's by
    # X2 = R X1 + t.
    point = np.array([0.3, -1.0, 4.0])
    in_camera = [
        np.linalg.inv(pose) @ np.append(point, 1.0) for pose in (camera_to_world1, camera_to_world2)
    ]
    np.testing.assert_allclose(
        rotation @ in_camera[0][:3] + translation, in_camera[1][:3], atol=1e-12
    )
    image1, image2 = _pair(2 * HEIGHT, 2 * WIDTH)
    outputs = predictor.predict(image1, image2, rotation=rotation, translation=translation)
    expected = model_lib.pose_parameters(
        rotation[None].astype(np.float32), (translation / np.linalg.norm(translation))[None]
    )
    np.testing.assert_allclose(outputs["global_params"], expected[0], atol=1e-5)
    # The odometry's metres set the scale when nothing else does.
    assert outputs["units"] == "metres"
    assert outputs["scale"] == pytest.approx(np.linalg.norm(translation), rel=1e-5)
    with pytest.raises(ValueError, match="give the pair's odometry"):
        predictor.predict(image1, image2)
    with pytest.raises(ValueError, match="not a rotation matrix"):
        predictor.predict(image1, image2, rotation=2 * rotation, translation=translation)
    with pytest.raises(ValueError, match="are for models trained given"):
        _given_pose_predictor("encoder").predict(
            image1, image2, rotation=rotation, translation=translation
        )


def test_a_model_on_the_pose_from_its_flow_gets_the_motion_at_its_own_resolution():
    from gld import geometry

    predictor = _given_pose_predictor("flow_pose")
    height, width = 2 * HEIGHT, 2 * WIDTH
    camera_matrix = np.array([[110.0, 0, 63.5], [0, 112.0, 47.5], [0, 0, 1]])
    grid = geometry.pixel_grid(height, width).astype(np.float64)
    depth = 3.0 + 0.01 * grid[..., 0] + 0.4 * np.sin(grid[..., 1] / 9.0)
    rotation = geometry.rotation_matrix(np.array([0.01, 0.03, -0.01]))
    translation = np.array([0.3, 0.05, 0.1])
    flow, _ = geometry.depth_to_flow(depth, camera_matrix, camera_matrix, rotation, translation)
    image1, image2 = _pair(height, width)
    with pytest.raises(ValueError, match="give intrinsics="):
        predictor.predict(image1, image2, flow.astype(np.float32))
    outputs = predictor.predict(image1, image2, flow.astype(np.float32), intrinsics=camera_matrix)
    pose = model_lib.global_params_pose(np.asarray(outputs["global_params"])[None])
    assert geometry.rotation_error_degrees(np.asarray(pose["rotation"][0]), rotation) < 0.5
    assert geometry.translation_error_degrees(np.asarray(pose["translation"][0]), translation) < 2.0


def _frames_moving_sideways(tmp_path):
    """Three frames of a camera moving 0.2 m then 0.3 m along x, and the plan of their
    consecutive pairs from those camera poses."""
    frames_dir = tmp_path / "frames"
    frames_dir.mkdir()
    image, _ = _pair(HEIGHT, WIDTH)
    paths = [frames_dir / f"f{index}.png" for index in range(3)]
    for index, path in enumerate(paths):
        cv2.imwrite(str(path), np.roll(image, 2 * index, axis=1))
    camera_to_world = np.tile(np.eye(4), (3, 1, 1))
    camera_to_world[:, 0, 3] = [0.0, 0.2, 0.5]
    plan = recordings.plan_recording(recordings.frame_pairs(3), camera_to_world=camera_to_world)
    return paths, plan


def test_a_recording_planned_from_camera_poses_gives_each_pair_its_odometry(tmp_path):
    predictor = _given_pose_predictor("pose")
    paths, plan = _frames_moving_sideways(tmp_path)
    assert plan.baselines == pytest.approx([0.2, 0.3])
    with pytest.raises(ValueError, match="with camera poses"):
        recordings.predict_recording(
            predictor,
            frames_lib.ImageFolderFrames(paths),
            recordings.plan_recording(
                recordings.frame_pairs(3), positions=[[0.0, 0, 0], [0.2, 0, 0], [0.5, 0, 0]]
            ),
            tmp_path / "refused",
            depth_format="npy",
        )
    out = tmp_path / "out"
    recordings.predict_recording(
        predictor, frames_lib.ImageFolderFrames(paths), plan, out, depth_format="npy"
    )
    read = lambda path: cv2.cvtColor(cv2.imread(str(path)), cv2.COLOR_BGR2RGB)  # noqa: E731
    expected = predictor(
        read(paths[1]), read(paths[2]), rotation=np.eye(3), translation=[-0.3, 0.0, 0.0]
    )
    np.testing.assert_allclose(np.load(out / "depth" / "f1__f2.npy"), expected, rtol=1e-5)


def test_a_model_refining_its_pose_on_the_flow_is_given_the_camera_it_saw():
    predictor = _given_pose_predictor("encoder", pose_refinement_steps=2)
    assert predictor.needs_camera and predictor.given_pose is None
    image1, image2 = _pair(2 * HEIGHT, 2 * WIDTH)
    with pytest.raises(ValueError, match="give intrinsics="):
        predictor.predict(image1, image2)
    camera_matrix = np.array([[110.0, 0, 63.5], [0, 112.0, 47.5], [0, 0, 1]])
    outputs = predictor.predict(image1, image2, intrinsics=camera_matrix)
    assert np.isfinite(outputs["depth"]).all()
    # The model saw the camera of its own resolution: half the focal length here.
    np.testing.assert_allclose(outputs["model_camera_matrix"][0, 0], 55.0)


def _halved(images):
    """[B, 2h, 2w, C] -> [B, h, w, C]: the area resize of an exact factor 2, the mean of
    each 2x2 block."""
    batch, height, width, channels = images.shape
    blocks = np.asarray(images, np.float64).reshape(batch, height // 2, 2, width // 2, 2, -1)
    return blocks.mean(axis=(2, 4))


@pytest.mark.parametrize("global_source", ["pose", "flow_pose"])
def test_a_model_reading_its_given_pose_against_the_flow_is_given_the_pose_and_camera(
    global_source,
):
    """A model given the pose (the odometry, or the essential matrix's of its flow) that
    derotates and triangulates the flow under it reads the pose and the cameras: the
    predictor gives it the odometry as the pose (unit t) and the normalised intrinsics of
    the camera resized to the model's resolution, as applying the model by hand does, and
    refuses a call without either in one line."""
    from gld import flow_pose, geometry

    predictor = _given_pose_predictor(global_source, derotate_flow=True, parallax_depth=True)
    model = predictor.model
    given = model_lib.GIVEN_POSE_INPUTS[global_source]
    assert model.extra_inputs == (*given, "intrinsics1", "intrinsics2")
    assert predictor.given_pose == global_source and predictor.needs_camera
    # Two pairs at twice the model's size, their flow that of a scene seen moving.
    height, width = 2 * HEIGHT, 2 * WIDTH
    camera_matrix = np.array([[110.0, 0, 63.5], [0, 112.0, 47.5], [0, 0, 1]])
    grid = geometry.pixel_grid(height, width).astype(np.float64)
    depth = 3.0 + 0.01 * grid[..., 0] + 0.4 * np.sin(grid[..., 1] / 9.0)
    rotations = np.stack(
        [geometry.rotation_matrix(np.array(v)) for v in ([0.01, 0.03, -0.01], [-0.02, 0.01, 0.0])]
    )
    translations = np.array([[0.3, 0.05, 0.1], [-0.1, 0.2, 0.05]])
    flows = np.stack(
        [
            geometry.depth_to_flow(depth, camera_matrix, camera_matrix, r, t)[0]
            for r, t in zip(rotations, translations, strict=True)
        ]
    ).astype(np.float32)
    pairs = [_pair(height, width, seed) for seed in (0, 1)]
    image1 = np.stack([pair[0] for pair in pairs])
    image2 = np.stack([pair[1] for pair in pairs])
    odometry = dict(rotation=rotations, translation=translations)
    if global_source != "pose":
        odometry = {}

    # By hand: frames and flow halved (the flow's pixels too); the camera halved keeps
    # its normalised intrinsics, (fx / W, fy / H, (cx + 0.5) / W, (cy + 0.5) / H).
    model_images = [_halved(image / 255.0) - 0.5 for image in (image1, image2)]
    model_flow = (_halved(flows) / 2).astype(np.float32)
    normalised = np.float32([110.0 / width, 112.0 / height, 64.0 / width, 48.0 / height])
    cameras = np.tile(normalised, (2, 1))
    if global_source == "pose":
        norms = np.linalg.norm(translations, axis=-1)
        pose = dict(rotation=rotations, translation=translations / norms[:, None])
    else:
        poses = [flow_pose.pose_of_example(flow, normalised, normalised) for flow in model_flow]
        pose = dict(
            flow_rotation=np.stack([p[0] for p in poses]),
            flow_translation=np.stack([p[1] for p in poses]),
        )
        assert all(p[2] for p in poses)
    pose = {key: np.asarray(value, np.float32) for key, value in pose.items()}

    def by_hand(**inputs):
        images = [np.asarray(image, np.float32) for image in model_images]
        return np.asarray(
            model.apply(predictor.variables, *images, model_flow, **inputs)["inv_depth"]
        )

    expected = by_hand(**pose, intrinsics1=cameras, intrinsics2=cameras)
    outputs = predictor.predict(image1, image2, flows, intrinsics=camera_matrix, **odometry)
    np.testing.assert_allclose(outputs["inv_depth"], expected, rtol=1e-4, atol=1e-6)
    np.testing.assert_allclose(outputs["model_camera_matrix"][0, 0], 55.0)
    if global_source == "pose":
        # The odometry's metres scale the depth.
        assert outputs["scale_source"] == "baseline"
        np.testing.assert_allclose(outputs["scale"], norms, rtol=1e-5)
    # The cameras and the pose both reach the depth: the camera of the input's size
    # normalised at the model's, or another pose, give another depth.
    unresized = 2 * cameras  # (fx / w, ...) at the model's w: twice the normalised
    wrong_camera = by_hand(**pose, intrinsics1=unresized, intrinsics2=unresized)
    assert not np.allclose(wrong_camera, expected, rtol=1e-3)
    other_pose = {key: value[::-1] for key, value in pose.items()}
    wrong_pose = by_hand(**other_pose, intrinsics1=cameras, intrinsics2=cameras)
    assert not np.allclose(wrong_pose, expected, rtol=1e-3)

    # What it lacks is named, in one line.
    messages = []
    with pytest.raises(ValueError, match="give intrinsics=") as refused:
        predictor.predict(image1, image2, flows, **odometry)
    messages.append(str(refused.value))
    if global_source == "pose":
        with pytest.raises(ValueError, match="give the pair's odometry") as refused:
            predictor.predict(image1, image2, flows, intrinsics=camera_matrix)
        messages.append(str(refused.value))
    else:
        with pytest.raises(ValueError, match="are for models trained given") as refused:
            predictor.predict(
                image1,
                image2,
                flows,
                intrinsics=camera_matrix,
                rotation=rotations,
                translation=translations,
            )
        messages.append(str(refused.value))
    assert all("\n" not in message for message in messages)


def test_a_recording_gives_a_model_reading_its_odometry_against_the_flow_both(tmp_path):
    """A recording's run gives a model given the odometry that reads it against the flow
    each pair's odometry and the camera, and refuses to start without the camera."""
    predictor = _given_pose_predictor("pose", derotate_flow=True, parallax_depth=True)
    paths, plan = _frames_moving_sideways(tmp_path)
    camera_matrix = np.array([[55.0, 0, 31.5], [0, 56.0, 23.5], [0, 0, 1]])
    with pytest.raises(ValueError, match="give the camera's intrinsics"):
        recordings.predict_recording(
            predictor,
            frames_lib.ImageFolderFrames(paths),
            plan,
            tmp_path / "refused",
            depth_format="npy",
        )
    out = tmp_path / "out"
    recordings.predict_recording(
        predictor,
        frames_lib.ImageFolderFrames(paths),
        plan,
        out,
        depth_format="npy",
        camera_matrix=camera_matrix,
    )
    read = lambda path: cv2.cvtColor(cv2.imread(str(path)), cv2.COLOR_BGR2RGB)  # noqa: E731
    expected = predictor(
        read(paths[1]),
        read(paths[2]),
        rotation=np.eye(3),
        translation=[-0.3, 0.0, 0.0],
        intrinsics=camera_matrix,
    )
    np.testing.assert_allclose(np.load(out / "depth" / "f1__f2.npy"), expected, rtol=1e-5)


@pytest.mark.parametrize(
    "extra_inputs",
    [
        ("rotation",),
        ("rotation", "translation", "flow_rotation", "flow_translation"),
        ("rotation", "translation", "intrinsics1", "intrinsics2", "depth"),
    ],
    ids=["half_a_pose", "two_poses", "an_unknown_key"],
)
def test_a_model_reading_what_a_predictor_cannot_give_is_refused(extra_inputs):
    import types

    model = types.SimpleNamespace(extra_inputs=extra_inputs)
    with pytest.raises(ValueError, match="which a predictor lacks"):
        DepthPredictor(model, {}, HEIGHT, WIDTH)
