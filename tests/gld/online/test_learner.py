"""The online learner and its run (gld/online/learner.py, run.py, checkpoint.py) on a
small simulated robot: prequential scores, determinism, updates beside prediction, resume."""

import itertools
import json
import shutil
import textwrap
import threading
import time

import jax
import numpy as np
import pytest
from conftest import TINY_MODEL, random_variables, run_on_cpu_devices

from data.gld_scenes import robot_stream
from gld import geometry
from gld.arguments import ArgumentError
from gld.losses.supervised import LossWeights
from gld.models import registry
from gld.online import labels as labels_lib
from gld.online import learner as learner_lib
from gld.online import offline, run
from gld.online.learner import OnlineLearner, OnlineSettings
from gld.online.stream import Frame

HEIGHT, WIDTH = 24, 32
# A short partner window and baseline: the robot moves about 3 cm a frame.
SETTINGS = dict(min_baseline=0.04, max_partner_gap=6, batch_size=2, capacity=16, seed=0)


@pytest.fixture(scope="module")
def stream():
    return robot_stream.SimulatedRobot(3, robot_stream.RobotSettings(height=HEIGHT, width=WIDTH))


@pytest.fixture(scope="module")
def frames(stream):
    return list(itertools.islice(stream.frames(), 24))


@pytest.fixture(scope="module")
def model_and_variables():
    model = registry.make_model("global_local", **TINY_MODEL)
    return model, random_variables(model, HEIGHT, WIDTH, seed=0)


def _learner(model_and_variables, **changes):
    model, variables = model_and_variables
    settings = OnlineSettings(**{**SETTINGS, **changes})
    return OnlineLearner(model, variables, settings, HEIGHT, WIDTH, LossWeights())


def _observe_all(learner, frames):
    rows = [learner.observe(frame) for frame in frames]
    learner.finish()
    return rows


def test_each_frame_is_predicted_and_scored_before_it_is_learned_from(model_and_variables, frames):
    learner = _learner(model_and_variables)
    rows = _observe_all(learner, frames)
    assert rows[0]["partner"] is None and "inv_depth" not in rows[0]  # no partner yet
    predicted = [row for row in rows if row["partner"] is not None]
    assert len(predicted) >= len(frames) - 3
    for row in predicted:
        assert row["baseline"] >= SETTINGS["min_baseline"]
        assert 0 < row["frame"] - row["partner"] <= SETTINGS["max_partner_gap"]
        assert np.isfinite(row["abs_inv"]) and np.isfinite(row["abs_inv_mean"])
    # The reading (not dropped) of each labelled frame joined the buffer, and each
    # labelled frame took one update: the first frame's prediction saw none.
    labelled = sum(row["labelled"] for row in predicted)
    assert learner.buffer.seen == labelled > 0
    assert learner.updates == len(predicted)
    # Scoring is prequential: frame t's score comes from the parameters before the
    # update it launched, so re-scoring it with the final model differs.
    frozen = _observe_all(_learner(model_and_variables, learn=False), frames)
    first = predicted[0]["frame"]
    assert frozen[first]["abs_inv"] == pytest.approx(rows[first]["abs_inv"], rel=1e-6)
    assert any(
        abs(a["abs_inv"] - b["abs_inv"]) > 1e-6
        for a, b in zip(frozen[first + 3 :], rows[first + 3 :], strict=True)
    )


@pytest.mark.slow
def test_the_worker_gives_the_same_run_as_updating_in_turn(model_and_variables, frames):
    together = _learner(model_and_variables, asynchronous=True)
    in_turn = _learner(model_and_variables, asynchronous=False)
    rows_together = _observe_all(together, frames[:12])
    rows_in_turn = [in_turn.observe(frame) for frame in frames[:12]]
    # In turn, frame t sees the updates up to t - 1; with the worker, up to t - 2.
    # Both see none at first, and their final parameters are the same updates.
    first = next(row["frame"] for row in rows_in_turn if row["partner"] is not None)
    assert rows_together[first]["abs_inv"] == pytest.approx(rows_in_turn[first]["abs_inv"])
    assert together.updates == in_turn.updates > 0
    for a, b in zip(
        jax.tree.leaves(together.published), jax.tree.leaves(in_turn.published), strict=True
    ):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-5, atol=1e-6)


# The learner of `_learner` on three CPU devices, its final parameters and the devices
# its state and its published variables lie on.
THREE_DEVICE_SCRIPT = textwrap.dedent(
    """
    import itertools, json, sys
    import jax, numpy as np
    sys.path.insert(0, "tests")
    from conftest import TINY_MODEL, random_variables
    from data.gld_scenes import robot_stream
    from gld.losses.supervised import LossWeights
    from gld.models import registry
    from gld.online.learner import OnlineLearner, OnlineSettings

    stream = robot_stream.SimulatedRobot(3, robot_stream.RobotSettings(height=24, width=32))
    model = registry.make_model("global_local", **TINY_MODEL)
    variables = random_variables(model, 24, 32, seed=0)
    settings = OnlineSettings(**SETTINGS, asynchronous=False)
    learner = OnlineLearner(model, variables, settings, 24, 32, LossWeights())
    for frame in itertools.islice(stream.frames(), 12):
        learner.observe(frame)
    leaves = jax.tree.leaves
    devices = lambda tree: sorted({device.id for leaf in leaves(tree) for device in leaf.devices()})
    print(json.dumps({
        "devices": learner.devices,
        "state_devices": devices(learner.state()["train_state"].params),
        "published_devices": devices(learner.published),
        "updates": learner.updates,
        "params": [np.asarray(leaf).ravel().tolist() for leaf in leaves(learner.published)],
    }))
    """
).replace("SETTINGS", repr(SETTINGS))


@pytest.mark.slow
def test_on_several_devices_updates_are_split_and_predictions_run_on_their_own(
    model_and_variables, frames
):
    numbers = run_on_cpu_devices(THREE_DEVICE_SCRIPT, 3)
    # The batch of 2 splits over the first two devices; the third predicts.
    assert numbers["devices"] == 2
    assert numbers["state_devices"] == [0, 1] and numbers["published_devices"] == [2]
    # The same updates as on one device, but for the float rounding of split sums (which
    # Adam turns into up to a step's size where a gradient is near zero).
    learner = _learner(model_and_variables, asynchronous=False)
    for frame in frames[:12]:
        learner.observe(frame)
    assert learner.devices == 1 and numbers["updates"] == learner.updates > 0
    flat = lambda leaves: np.concatenate([np.ravel(leaf) for leaf in leaves])
    split = flat(numbers["params"])
    whole = flat(jax.tree.leaves(learner.published))
    start = flat(jax.tree.leaves(model_and_variables[1]))
    assert np.linalg.norm(split - whole) < 0.01 * np.linalg.norm(whole - start)


def _keys_predicted_on(learner):
    """The batch keys of each prediction `learner` makes from now on."""
    seen, predict = [], learner._predict

    def recorded(variables, batch):
        seen.append(set(batch))
        return predict(variables, batch)

    learner._predict = recorded
    return seen


def test_the_flow_pose_reaches_the_model_that_reads_it_first_and_the_loss_after_the_depth(
    model_and_variables, frames
):
    from gld import flow as flow_lib
    from gld import flow_pose

    # The main job's loss reads the flow's pose (its pose teacher), its model does not:
    # the prediction goes without it, the stored pair gets it.
    model, variables = model_and_variables
    settings = OnlineSettings(**{**SETTINGS, "asynchronous": False, "capacity": 32})
    learner = OnlineLearner(model, variables, settings, HEIGHT, WIDTH, LossWeights(pose_teacher=1))
    seen = _keys_predicted_on(learner)
    rows = [learner.observe(frame) for frame in frames]
    assert seen and all("flow_rotation" not in keys for keys in seen)
    stored = learner.buffer.state()["arrays"]
    intrinsics = np.asarray(frames[0].intrinsics, np.float32)
    labelled = [row for row in rows if row.get("labelled")]
    succeeded = 0
    for slot, row in enumerate(labelled):  # the reservoir is not full: in arrival order
        flow = flow_lib.estimate(frames[row["frame"]].image, frames[row["partner"]].image)
        rotation, translation, good = flow_pose.pose_of_example(flow, intrinsics, intrinsics)
        np.testing.assert_allclose(stored["flow_rotation"][slot], rotation, atol=1e-6)
        np.testing.assert_allclose(stored["flow_translation"][slot], translation, atol=1e-6)
        succeeded += good
    assert succeeded >= 3  # not the placeholders alone (identity, zero)
    # A model whose g is the flow's pose gets it before its prediction.
    reader = registry.make_model("global_local", global_source="flow_pose", **TINY_MODEL)
    pose = {"flow_rotation": np.eye(3)[None], "flow_translation": np.ones((1, 3))}
    start = random_variables(reader, HEIGHT, WIDTH, seed=0, **pose)
    learner = OnlineLearner(reader, start, settings, HEIGHT, WIDTH, LossWeights())
    seen = _keys_predicted_on(learner)
    for frame in frames[:8]:
        learner.observe(frame)
    assert seen and all("flow_rotation" in keys for keys in seen)


def test_a_prediction_is_served_while_an_update_runs(model_and_variables, frames):
    learner = _learner(model_and_variables)
    spans, predictions = [], []
    run_updates, predict = learner._run_updates, learner._predict

    def slow_updates(state, batches):
        start = time.perf_counter()
        time.sleep(0.5)
        result = run_updates(state, batches)
        spans.append((start, time.perf_counter(), threading.current_thread()))
        return result

    def timed_predict(variables, batch):
        result = predict(variables, batch)
        predictions.append((time.perf_counter(), threading.current_thread()))
        return result

    learner._run_updates, learner._predict = slow_updates, timed_predict
    _observe_all(learner, frames[:6])
    assert spans and all(thread is not threading.current_thread() for *_, thread in spans)
    served_during = [
        when for when, _ in predictions if any(start < when < end for start, end, _ in spans)
    ]
    assert served_during  # predictions ran while an update slept in the worker


def _summaryless(rows):
    return [{k: v for k, v in row.items() if not k.endswith("_ms")} for row in rows]


# Readings carried over 7 frames: more than the partner window's 6, so a resumed run
# must replay the frames before its position for the memory, not only for the partners.
@pytest.mark.slow
@pytest.mark.parametrize("reading_memory", [0, 7])
def test_a_run_stopped_after_a_checkpoint_resumes_to_the_same_result(
    model_and_variables, stream, tmp_path, reading_memory
):
    arguments = dict(frames=16, checkpoint_every=8, window=8, meta={}, progress=False)

    def learner():
        return _learner(model_and_variables, reading_memory=reading_memory)

    whole = tmp_path / "whole"
    run.run_online(stream, learner(), whole, **arguments)
    # A run killed after its checkpoint at 8 and before the one at 12: its log runs on.
    stopped = tmp_path / "stopped"
    run.run_online(stream, learner(), stopped, **{**arguments, "frames": 12})
    shutil.rmtree(stopped / "checkpoints" / "12")
    assert len((stopped / run.LOG_FILE).read_text().splitlines()) == 12
    lines = []
    resumed = run.run_online(stream, learner(), stopped, **arguments, print_fn=lines.append)

    def rows(workdir):
        return [json.loads(line) for line in (workdir / run.LOG_FILE).read_text().splitlines()]

    updates = rows(whole)[7]["updates"]
    assert updates > 0 and lines == [f"resumed {stopped} at frame 8 ({updates} updates)"]

    assert [row["frame"] for row in rows(stopped)] == list(range(16))
    assert _summaryless(rows(stopped)) == _summaryless(rows(whole))
    summary = json.loads((whole / run.SUMMARY_FILE).read_text())
    assert resumed["curve"] == summary["curve"] and resumed["labelled"] == summary["labelled"]
    assert (stopped / run.CURVE_FILE).is_file()


@pytest.mark.slow
def test_a_run_is_resumed_only_as_it_was_made(model_and_variables, stream, tmp_path):
    arguments = dict(frames=8, checkpoint_every=4, window=4, progress=False)
    meta = {"model": "tiny", "settings": {"reading_memory": 0, "batch_size": 2}}
    run.run_online(stream, _learner(model_and_variables), tmp_path, meta=meta, **arguments)
    log = (tmp_path / run.LOG_FILE).read_text()
    other = {"model": "tiny", "settings": {"reading_memory": 30, "batch_size": 2}}
    with pytest.raises(ArgumentError, match=r"settings.reading_memory 0 -> 30\)"):
        run.run_online(
            stream,
            _learner(model_and_variables, reading_memory=30),
            tmp_path,
            meta=other,
            **{**arguments, "frames": 12},
        )
    assert (tmp_path / run.LOG_FILE).read_text() == log  # nothing written
    # The same run resumes.
    run.run_online(
        stream, _learner(model_and_variables), tmp_path, meta=meta, **{**arguments, "frames": 12}
    )
    assert len((tmp_path / run.LOG_FILE).read_text().splitlines()) == 12


def test_bad_settings_are_refused():
    with pytest.raises(ValueError, match="min_baseline must be > 0 metres"):
        OnlineSettings(min_baseline=0)
    with pytest.raises(ValueError, match="batch_size must be >= 1"):
        OnlineSettings(batch_size=0)
    with pytest.raises(ValueError, match="reading_memory must be >= 0"):
        OnlineSettings(reading_memory=-1)
    with pytest.raises(ValueError, match="anchor must be in"):
        OnlineSettings(anchor=1.0)
    with pytest.raises(ValueError, match="warmup must be >= 0"):
        OnlineSettings(warmup=-1)
    with pytest.raises(ValueError, match="max_rotation must be >= 0 degrees"):
        OnlineSettings(max_rotation=-5)
    for teacher in ({"teacher_labels": -1}, {"teacher_parallax": 0.0}):
        with pytest.raises(ValueError, match="teacher_labels must be >= 0 and teacher_parallax"):
            OnlineSettings(**teacher)


def _distance(variables, start):
    moved = jax.tree.map(
        lambda a, b: np.sum((np.asarray(a) - np.asarray(b)) ** 2), variables, start
    )
    return float(np.sqrt(sum(jax.tree.leaves(moved["params"]))))


@pytest.mark.slow
def test_anchored_or_warming_up_the_learner_stays_nearer_its_start(model_and_variables, frames):
    start = model_and_variables[1]
    free = _learner(model_and_variables, asynchronous=False)
    _observe_all(free, frames[:12])
    moved = _distance(free.published, start)
    anchored = _learner(model_and_variables, asynchronous=False, anchor=0.5)
    _observe_all(anchored, frames[:12])
    assert anchored.updates == free.updates > 0
    assert 0 < _distance(anchored.published, start) < 0.7 * moved
    # Over a warm-up of 1,000 updates the first ten take at most 1% of the rate each.
    warming = _learner(model_and_variables, asynchronous=False, warmup=1000)
    _observe_all(warming, frames[:12])
    assert warming.updates == free.updates
    assert 0 < _distance(warming.published, start) < 0.1 * moved


def _frame(index, translation, reading=None, rotation=None):
    """A frame of a 32x24 camera (fx = fy = 20 px, centre (16, 12)) at `translation`
    (world-to-camera; no rotation unless given)."""
    return Frame(
        index=index,
        time=index / 10,
        image=np.zeros((HEIGHT, WIDTH, 3), np.uint8),
        rotation=np.eye(3) if rotation is None else rotation,
        translation=np.asarray(translation, np.float64),
        intrinsics=np.array([20 / WIDTH, 20 / HEIGHT, 16.5 / WIDTH, 12.5 / HEIGHT]),
        reading=reading,
    )


def _turning(step, headings):
    """Frames of a robot moving `step` metres a frame along x, turned about y by each
    of `headings` (degrees) in turn."""
    frames = []
    for index, heading in enumerate(headings):
        rotation = geometry.rotation_matrix(np.radians([0.0, heading, 0.0]))
        center = np.array([step * index, 0.0, 0.0])
        frames.append(_frame(index, -rotation @ center, rotation=rotation))
    return frames


STEADY_TURN = [4.0 * index for index in range(8)]  # 4 deg a frame
BEND = [0, 6, 12, 18, 12, 6, 0]  # out and back: frame 1 is heading as the last one


@pytest.mark.parametrize(
    "step, headings, max_rotation, back",
    [
        (0.02, STEADY_TURN, 0.0, 3),  # no limit: the newest 5 cm away (6 cm, turned 12 deg)
        (0.02, STEADY_TURN, 20.0, 3),  # within the limit already
        (0.02, STEADY_TURN, 10.0, 2),  # the farthest nearer within 10 deg: 4 cm, >= 2.5 cm
        (0.01, STEADY_TURN, 10.0, 5),  # within 10 deg only 2 cm: the partner without the limit
        (0.03, BEND, 10.0, 1),  # never farther back: not frame 1 (15 cm, 6 deg) but frame 5
    ],
)
def test_a_sharp_turn_takes_a_nearer_partner(
    model_and_variables, step, headings, max_rotation, back
):
    frames = _turning(step, headings)
    turn = geometry.rotation_error_degrees(frames[-4].rotation, frames[-1].rotation)
    assert turn == pytest.approx(abs(headings[-1] - headings[-4]))
    learner = _learner(model_and_variables, min_baseline=0.05, max_rotation=max_rotation)
    learner.next_frame = frames[-1].index
    for frame in frames[:-1]:
        learner.resume_from(frame)
    partner, distance = learner._partner(frames[-1])
    assert partner.index == frames[-1].index - back
    assert distance == pytest.approx(step * back)


def test_a_reading_is_carried_to_where_the_odometry_puts_its_point():
    # Read 4 m ahead at pixel (26, 12), 10 px right of the centre: the point (2, 0, 4).
    first = _frame(0, [0.0, 0.0, 0.0], reading=(26.0, 12.0, 4.0))
    point = labels_lib.reading_point(first)
    np.testing.assert_allclose(point, [2.0, 0.0, 4.0])
    # The camera 1 m further on (world-to-camera t = -c): the point is 3 m ahead and has
    # moved out from the expansion's centre, u = 16 + 20 * 2 / 3 = 29.3 -> column 29.
    labels = labels_lib.carried_labels(_frame(1, [0.0, 0.0, -1.0]), point[None], 24, 32)
    np.testing.assert_allclose(labels, [[12.0, 29.0, 3.0]])
    # 2 m on, u = 16 + 20 * 2 / 2 = 36 is outside the 32-pixel image; 5 m on, the point is
    # behind the camera: nothing.
    assert not len(labels_lib.carried_labels(_frame(1, [0.0, 0.0, -2.0]), point[None], 24, 32))
    behind = _frame(1, [0.0, 0.0, -5.0])
    assert not len(labels_lib.carried_labels(behind, point[None], 24, 32))


def test_carried_readings_agree_with_the_rendered_depth(model_and_variables, frames):
    """On the simulated robot, the labels a frame gets from earlier readings hold the
    depth the renderer gives at their pixels, within the sensor's 1% noise and the
    odometry's drift."""
    learner = _learner(model_and_variables, reading_memory=10, learn=False)
    errors, carried = [], 0
    for frame in frames:
        labels = learner.labels_of(frame, baseline=1.0)
        learner.observe(frame, predict=False)
        carried += max(0, len(labels) - (frame.reading is not None))
        for row, column, depth in labels:
            errors.append(depth / frame.depth[int(row), int(column)] - 1)
    errors = np.abs(errors)
    assert carried > len(frames)  # more than one carried label a frame (24x32 frames)
    assert np.median(errors) < 0.03 and np.mean(errors < 0.1) > 0.95


def test_the_offline_reference_trains_on_every_pair_and_scores_both_models(
    model_and_variables, stream, frames
):
    model, variables = model_and_variables

    def make_learner(**changes):
        start = changes.pop("variables", variables)
        settings = OnlineSettings(**{**SETTINGS, **changes})
        return OnlineLearner(model, start, settings, HEIGHT, WIDTH, LossWeights())

    online = _learner(model_and_variables)
    rows = _observe_all(online, frames[:12])
    result = offline.offline_reference(
        stream, make_learner, frames=12, updates=5, online_variables=online.published
    )
    # Every labelled pair is kept (the buffer holds them all), and the steps are as asked.
    assert result["pairs"] == sum(bool(row.get("labelled")) for row in rows) > 0
    assert result["updates"] == 5
    for name in ("offline", "online"):
        assert 0 < result[name]["abs_inv"] and result[name]["x_mean"] > 0
    untrained = offline.score_frozen(make_learner(learn=False), stream, 12)
    assert result["offline"]["abs_inv"] != pytest.approx(untrained["abs_inv"], rel=1e-6)
    with pytest.raises(ValueError, match="learn=False"):
        offline.score_frozen(make_learner(), stream, 12)


def test_a_restored_learner_carries_the_readings_of_the_frames_it_replays(
    model_and_variables, frames
):
    """`history` frames replayed into a restored learner give it the reading memory of
    the learner it was saved from; the partner window's frames alone would not."""
    whole = _learner(model_and_variables, reading_memory=12, learn=False)
    for frame in frames[:16]:
        whole.observe(frame, predict=False)
    assert whole.history == 12

    def restored(replayed: int) -> OnlineLearner:
        learner = _learner(model_and_variables, reading_memory=12, learn=False)
        learner.restore(whole.state())
        for frame in frames[16 - replayed : 16]:
            learner.resume_from(frame)
        return learner

    def labels(learner):
        return [learner.labels_of(frame, baseline=1.0).tolist() for frame in frames[16:20]]

    expected = labels(whole)
    assert labels(restored(whole.history)) == expected
    assert labels(restored(SETTINGS["max_partner_gap"])) != expected


def _true_flow(frames):
    """A stand-in for DIS that gives the exact flow between two of `frames`."""
    by_image = {frame.image.tobytes(): frame for frame in frames}

    def true_flow(image1, image2):
        frame, partner = by_image[image1.tobytes()], by_image[image2.tobytes()]
        rotation, translation = _true_motion(frame, partner)
        flow, _ = geometry.ground_truth_flow(
            frame.depth, None, frame.intrinsics, partner.intrinsics, rotation, translation
        )
        return flow

    return true_flow


def _true_motion(frame, partner):
    return geometry.relative_pose(
        frame.true_rotation, frame.true_translation, partner.true_rotation, partner.true_translation
    )


def test_the_classical_references_are_scored_on_the_learners_pairs_and_change_nothing_else(
    model_and_variables, frames, monkeypatch
):
    plain = _observe_all(_learner(model_and_variables, learn=False), frames)
    # With the true flow in place of DIS, the flow triangulated under the true pose is the
    # truth, and so is the essential matrix's pipeline where its pose does not fail (on
    # these 32x24 images it often finds too few correspondences; a failed pair is scored
    # as the running reference): the references are in the learner's units (the true
    # baseline's) and read the pair the learner read.
    monkeypatch.setattr(learner_lib.flow_lib, "estimate", _true_flow(frames))
    exact = _observe_all(_learner(model_and_variables, learn=False, references=True), frames)
    scored = [row for row in exact if "abs_inv" in row]
    assert scored
    for row in scored:
        assert row["abs_inv_triangulation_gt_pose"] < 1e-3 * row["abs_inv_mean"]
        assert row["abs_inv_sfm_flow"] < 1e-3 * row["abs_inv_mean"] or (
            row["abs_inv_sfm_flow"] == row["abs_inv_mean"]
        )
    assert sum(row["abs_inv_sfm_flow"] < 1e-3 * row["abs_inv_mean"] for row in scored) >= 5
    monkeypatch.undo()
    # On DIS's flow, the learner's own predictions and scores are those of a run without
    # the references.
    with_references = _observe_all(
        _learner(model_and_variables, learn=False, references=True), frames
    )
    for a, b in zip(plain, with_references, strict=True):
        assert a.get("abs_inv") == b.get("abs_inv")
        assert ("abs_inv_sfm_flow" in b) == ("abs_inv" in b)


def test_the_curve_gives_the_medians_and_the_references_where_the_rows_hold_them():
    rows = [
        {"frame": 0, "abs_inv": 1.0, "abs_inv_mean": 1.0, "abs_inv_sfm_flow": 9.0},
        {"frame": 1, "abs_inv": 1.0, "abs_inv_mean": 2.0, "abs_inv_sfm_flow": 1.0},
        {"frame": 2, "abs_inv": 3.0, "abs_inv_mean": 2.0, "abs_inv_sfm_flow": 0.5},
        {"frame": 3, "abs_inv": 2.0, "abs_inv_mean": 1.0},
    ]
    first, second = run.curve(rows, window=3)
    assert first["x_mean"] == pytest.approx(5 / 5)
    assert first["median_x_mean"] == pytest.approx(1.0)  # of 1, 0.5, 1.5
    assert first["sfm_flow_x_mean"] == pytest.approx(10.5 / 5)  # one frame's explosion
    assert first["sfm_flow_median_x_mean"] == pytest.approx(0.5)  # of 9, 0.5, 0.25
    assert "triangulation_gt_pose_x_mean" not in first
    assert second["median_x_mean"] == 2.0 and "sfm_flow_x_mean" not in second


def test_the_sustained_frame_rate_leaves_out_the_first_window():
    # Four frames that compile (1 s each), then six at 0.1 s: 10 frames/s sustained.
    rows = [{"frame": index, "updates": index, "update_wait_ms": 0.0} for index in range(10)]
    for row in rows:
        row["frame_ms"] = 1000.0 if row["frame"] < 4 else 100.0
    summary = run.summarise(rows, window=4, seconds=4.6)
    assert summary["sustained_frames_per_second"] == pytest.approx(10.0)
    assert summary["frames_per_second"] == pytest.approx(10 / 4.6)
    assert summary["frame_ms"] == {"p50": 100.0, "p90": 1000.0}
    # A run no longer than its window: all of it.
    assert run.summarise(rows[:4], window=4, seconds=4.0)["sustained_frames_per_second"] == 1.0


def test_the_teacher_labels_a_pair_after_its_reading_with_the_depth_its_flow_gives(
    model_and_variables, frames, monkeypatch
):
    """With the exact flow, each teacher's label is the true depth at its pixel in the
    pair's true baseline, stored after the frame's own reading, one label a pixel."""
    monkeypatch.setattr(learner_lib.flow_lib, "estimate", _true_flow(frames))
    learner = _learner(model_and_variables, learn=False, teacher_labels=6, teacher_parallax=0.5)
    added = []
    monkeypatch.setattr(learner.buffer, "add", added.append)
    rows = _observe_all(learner, frames)
    by_image = {frame.image.tobytes(): frame for frame in frames}
    taught = 0
    for pair, row in zip(added, [row for row in rows if row.get("labelled")], strict=True):
        frame, partner = by_image[pair.image1.tobytes()], by_image[pair.image2.tobytes()]
        labels = pair.labels
        assert len(np.unique(labels[:, :2], axis=0)) == len(labels) <= 7
        if frame.reading is not None:
            u, v, distance = frame.reading
            np.testing.assert_allclose(labels[0], [round(v), round(u), distance / row["baseline"]])
            labels = labels[1:]
        true_baseline = np.linalg.norm(_true_motion(frame, partner)[1])
        rows_, columns = labels[:, 0].astype(int), labels[:, 1].astype(int)
        np.testing.assert_allclose(
            labels[:, 2] * true_baseline, frame.depth[rows_, columns], rtol=1e-2
        )
        taught += len(labels) > 0
    assert taught >= 3  # the essential matrix holds on some of these 32x24 pairs
