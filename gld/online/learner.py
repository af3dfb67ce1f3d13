"""The online learner: depth for every new frame now, learning from its range reading next.

    learner = OnlineLearner(model, variables, OnlineSettings(), height=96, width=128)
    for frame in stream.frames():
        result = learner.observe(frame)    # the published depth, its score, timings
    learner.finish()                       # waits for the update in flight

For each frame the learner picks its partner, the newest earlier frame (within
`max_partner_gap`) whose odometry puts the camera at least `min_baseline` metres away
(and, with `max_rotation`, turned no more than that from the frame: `_partner`),
computes the flow from the frame to the partner (OpenCV DIS, as the datasets), predicts
the frame's depth with the model as it is and publishes it (in baselines; times the
odometry's baseline, metres). In simulation the prediction is then scored against the
truth, before anything is learned from the frame (prequential). The pair, with its range
reading as a labelled pixel (camera-z metres over the odometry's baseline: the model's
units), and with the readings of up to `reading_memory` earlier frames carried into it by
the odometry, goes into a bounded replay buffer (`gld.online.replay`), and
`updates_per_frame` optimiser steps run on batches of the newest pair and replayed ones.

The updates run in a worker thread beside the next frames: a prediction never waits for
one. The update launched at frame t runs while frame t + 1 is predicted and is joined
(its parameters swapped in whole) after that prediction is published, so frame t's depth
comes from the parameters of the updates up to frame t - 2. The order of operations is
fixed, so a run is deterministic for a stream and a seed, with the worker or without
(`asynchronous=False` runs each update at once, for the same results). With several
devices (on the CPU, cores made devices by `gld.sharding.split_cpu_devices`), the
updates run data-parallel over all but the last, which predicts alone: a device running
its share of an update would hold a prediction up until the update is done. Results
depend on the update's device count at the level of float rounding.

`state()` and `restore()` hold everything a resumed run needs besides the stream (the
model and optimiser state, the buffer, the running reference, counters); the stream is
replayed from the recorded position (`next_frame`), after the `history` frames before it
refill the partner window and the reading memory (`resume_from`).
"""

from __future__ import annotations

import collections
import concurrent.futures
import dataclasses
import time
from typing import Any

import flax.linen as nn
import jax
import numpy as np
import optax

from gld import flow as flow_lib
from gld import flow_pose, geometry, sharding
from gld.losses import supervised as losses
from gld.models import layers
from gld.online import labels as labels_lib
from gld.online import references, teacher
from gld.online.replay import VECTOR_FIELDS, LabelledPair, ReplayBuffer
from gld.online.stream import Frame
from gld.runs import optimizer as optimizer_lib
from gld.runs import state as state_lib
from gld.runs.state import TrainState
from gld.training import trainer


@dataclasses.dataclass(frozen=True)
class OnlineSettings:
    """How the learner pairs frames and learns.

    Attributes:
      min_baseline: metres of odometry between a frame and its partner.
      max_partner_gap: how many frames back a partner may be.
      max_rotation: degrees the odometry may turn between a frame and its partner; 0 =
        any. In a sharp turn the frame `min_baseline` back can have turned further than
        the pairs a model was trained on (`gld_scenes` pairs turn less than 10 degrees),
        where the search of g fails; the partner is then the farthest nearer frame
        within the turn if it is at least half of `min_baseline` away, else the frame
        without the limit (never a farther frame: one that turned back after a bend is
        far and sees the room from elsewhere).
      batch_size: pairs per update (the newest and replayed ones).
      updates_per_frame: optimiser steps after each labelled frame.
      capacity: the replay buffer's pairs.
      zoom: each replayed pair is a random crop of at least this fraction of each side
        holding its labelled pixel, resized back (`ReplayBuffer.batch`): a sensor that
        reads one fixed pixel then labels the whole image; 1 = no crop.
      learning_rate: Adam's, constant after the warm-up.
      warmup: updates over which the rate rises linearly from 0 to `learning_rate`:
        Adam's first steps from fresh moments move every parameter by about the full
        rate whatever its gradient, which a pretrained model's first updates feel; 0 =
        none.
      anchor: each update also takes this fraction of every parameter's distance from
        its starting value (a pretrained model's) back (L2-SP, decoupled:
        `optimizer.toward_start`); 0 = none.
      reading_memory: the range readings of up to this many earlier frames also label
        each new frame: each reading's point, placed in the world by its frame's
        odometry, is projected into the new frame by the new frame's odometry
        (`carried_labels`). A forward-looking robot's sensor reads where its flow has
        no parallax (the expansion's centre); the points it read earlier have moved out
        from there, to pixels whose flow carries their depth. 0 = only the frame's own
        reading.
      teacher_labels, teacher_parallax: each new pair also gets up to `teacher_labels`
        labels from the classical pipeline on its own flow (`gld.online.teacher`: the
        essential matrix's pose), where its parallax is at least `teacher_parallax` px.
      learn: False keeps the model as given (the frozen reference).
      references: also score the classical references on each pair (simulation only,
        `gld.online.references`: the essential matrix's pipeline on the pair's flow, and
        the flow triangulated under the true pose), after the prediction is published:
        the latency is not touched, the frame rate is (a RANSAC and two triangulations
        a frame).
      asynchronous: run updates in a worker thread beside the next frames.
      seed: the buffer's sampling and the train steps' randomness.
    """

    min_baseline: float = 0.05
    max_partner_gap: int = 20
    max_rotation: float = 0.0
    batch_size: int = 4
    updates_per_frame: int = 1
    capacity: int = 256
    zoom: float = 0.5
    learning_rate: float = 5e-4
    warmup: int = 0
    anchor: float = 0.0
    reading_memory: int = 0
    teacher_labels: int = 0
    teacher_parallax: float = 1.0
    learn: bool = True
    references: bool = False
    asynchronous: bool = True
    seed: int = 0

    def __post_init__(self):
        if self.warmup < 0:
            raise ValueError(f"warmup must be >= 0, got {self.warmup}")
        for name in ("max_partner_gap", "batch_size", "capacity"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        if self.teacher_labels < 0 or not self.teacher_parallax > 0:
            got = f"{self.teacher_labels} and {self.teacher_parallax}"
            raise ValueError(f"teacher_labels must be >= 0 and teacher_parallax > 0, got {got}")
        if self.reading_memory < 0:
            raise ValueError(f"reading_memory must be >= 0, got {self.reading_memory}")
        if self.updates_per_frame < 0:
            raise ValueError(f"updates_per_frame must be >= 0, got {self.updates_per_frame}")
        if not self.max_rotation >= 0:
            raise ValueError(f"max_rotation must be >= 0 degrees, got {self.max_rotation}")
        if not self.min_baseline > 0:
            raise ValueError(f"min_baseline must be > 0 metres, got {self.min_baseline}")
        if not 0 < self.zoom <= 1:
            raise ValueError(f"zoom must be in (0, 1], got {self.zoom}")
        if not self.learning_rate > 0:
            raise ValueError(f"learning_rate must be > 0, got {self.learning_rate}")
        if not 0 <= self.anchor < 1:
            raise ValueError(f"anchor must be in [0, 1), got {self.anchor}")


class OnlineLearner:
    """Predicts each frame's depth and learns from its range reading (module docstring)."""

    def __init__(
        self,
        model: nn.Module,
        variables: dict[str, Any],
        settings: OnlineSettings,
        height: int,
        width: int,
        loss_weights: Any = None,
    ):
        self.model, self.settings = model, settings
        self.height, self.width = height, width
        if loss_weights is None:
            loss_weights = losses.LossWeights()
        self.self_supervised = trainer.loss_name(model) == "self_supervised"
        self.keys = trainer.batch_keys(model, loss_weights)
        self._model_keys = layers.input_keys(model)  # what a prediction reads
        optimizer = optimizer_lib.make_optimizer(
            settings.learning_rate, "constant", warmup_steps=settings.warmup
        )
        if settings.anchor:
            optimizer = optax.chain(optimizer, optimizer_lib.toward_start(settings.anchor))
        # Predictions on the last device, updates over the others the batch splits over.
        devices = jax.local_devices()
        self._prediction_device = devices[-1]
        if len(devices) > 1:
            devices = devices[:-1]
        count = sharding.devices_for_batch(settings.batch_size, len(devices))
        self._mesh = sharding.make_mesh(devices[:count])
        self._state = self._placed(state_lib.state_of(variables, optimizer, settings.seed))
        step = trainer.make_train_step(model=model, optimizer=optimizer, loss_weights=loss_weights)
        self._train_step = sharding.under_mesh(jax.jit(step), self._mesh)
        self._predict = jax.jit(
            lambda variables, batch: layers.apply_model(model, variables, batch, train=False)[
                "inv_depth"
            ]
        )
        self.published = self._published()
        self._teacher = teacher.TeacherSettings(settings.teacher_labels, settings.teacher_parallax)
        labels = 1 + settings.reading_memory + settings.teacher_labels
        self.buffer = ReplayBuffer(settings.capacity, height, width, settings.seed, labels)
        self._window: collections.deque[Frame] = collections.deque(maxlen=settings.max_partner_gap)
        # The world points of the last `reading_memory` frames' readings (None: no reading).
        self._memory: collections.deque[np.ndarray | None] = collections.deque(
            maxlen=settings.reading_memory
        )
        self._worker = concurrent.futures.ThreadPoolExecutor(1) if settings.asynchronous else None
        self._pending: concurrent.futures.Future | None = None
        self.next_frame = 0  # the stream position of the next frame to observe
        self.updates = 0
        self._reference_sum, self._reference_count = 0.0, 0
        self._references = references.StreamReferences() if settings.references else None

    @property
    def devices(self) -> int:
        """The devices an update runs on (predictions run on one more, where there is one)."""
        return self._mesh.devices.size

    # ------------------------------------------------------------------ pairs

    def _partner(self, frame: Frame) -> tuple[Frame, float] | None:
        """The frame's partner in the window and the odometry's distance to it: the newest
        frame at least `min_baseline` away, or in a sharp turn a nearer one
        (`max_rotation`; see `OnlineSettings`)."""
        settings = self.settings
        within = None  # the farthest frame within the turn's limit, nearer than the partner
        for candidate in reversed(self._window):
            distance = float(np.linalg.norm(frame.center - candidate.center))
            turned = settings.max_rotation and (
                geometry.rotation_error_degrees(candidate.rotation, frame.rotation)
                > settings.max_rotation
            )
            if distance >= settings.min_baseline:
                if turned and within and within[1] >= settings.min_baseline / 2:
                    return within
                return candidate, distance
            if not turned and (within is None or distance > within[1]):
                within = candidate, distance
        return None

    def _pair(self, frame: Frame, partner: Frame) -> tuple[dict[str, np.ndarray], float]:
        """The example contract's fields of (frame, partner) for the model, with the
        odometry's relative pose at ||t|| = 1, and the odometry's baseline."""
        flow = flow_lib.estimate(frame.image, partner.image)
        rotation, translation = geometry.relative_pose(
            frame.rotation, frame.translation, partner.rotation, partner.translation
        )
        baseline = float(np.linalg.norm(translation))
        example = {
            "image1": frame.image.astype(np.float32) / 255.0 - 0.5,
            "image2": partner.image.astype(np.float32) / 255.0 - 0.5,
            "flow": flow,
            "intrinsics1": np.asarray(frame.intrinsics, np.float32),
            "intrinsics2": np.asarray(partner.intrinsics, np.float32),
            "rotation": np.asarray(rotation, np.float32),
            "translation": np.asarray(translation / baseline, np.float32),
        }
        if "flow_rotation" in self._model_keys:
            self._add_flow_pose(example)
        return example, baseline

    def _add_flow_pose(self, example: dict[str, np.ndarray]) -> None:
        """Adds the essential matrix's pose of the pair's flow (`gld.flow_pose`) where the
        model or its loss reads it (placeholders where neither does), once. A model that
        does not read it gets it after its depth is published: a RANSAC off the latency."""
        if "flow_rotation" in example:
            return
        if "flow_rotation" in self.keys:
            flow_rotation, flow_translation, _ = flow_pose.pose_of_example(
                example["flow"], example["intrinsics1"], example["intrinsics2"]
            )
            example["flow_rotation"] = np.asarray(flow_rotation, np.float32)
            example["flow_translation"] = np.asarray(flow_translation, np.float32)
        else:
            example["flow_rotation"] = np.eye(3, dtype=np.float32)
            example["flow_translation"] = np.zeros(3, np.float32)

    @property
    def history(self) -> int:
        """Frames before a position that a resumed run replays (`resume_from`): the
        partner window's and the reading memory's."""
        return max(self.settings.max_partner_gap, self.settings.reading_memory)

    def labels_of(self, frame: Frame, baseline: float) -> np.ndarray:
        """[N, 3] (row, column, depth in baselines): the frame's range reading first,
        then the earlier readings carried into it (`reading_memory`)."""
        own = np.zeros((0, 3), np.float32)
        if frame.reading is not None:
            u, v, distance = frame.reading
            row, column = int(round(v)), int(round(u))
            if not (0 <= row < self.height and 0 <= column < self.width and distance > 0):
                raise ValueError(
                    f"frame {frame.index}: reading {frame.reading} is not in the image"
                )
            own = np.array([[row, column, distance]], np.float32)
        points = [point for point in self._memory if point is not None]
        points = np.array(points).reshape(-1, 3)
        carried = labels_lib.carried_labels(frame, points, self.height, self.width)
        # One label a pixel: the frame's own reading, else the newest carried point.
        labels = labels_lib.first_per_pixel(np.concatenate([own, carried]))
        labels[:, 2] /= baseline
        return labels

    def _remember(self, frame: Frame) -> None:
        if self.settings.reading_memory:
            self._memory.appendleft(labels_lib.reading_point(frame))

    # ----------------------------------------------------------------- scoring

    def _score(
        self,
        frame: Frame,
        inv_depth: np.ndarray,
        true_translation: np.ndarray,
        others: dict[str, np.ndarray | None],
    ) -> dict[str, float]:
        """Abs-Inv of the prediction against the truth in the true baseline's units (the
        norm of `true_translation`, the true motion from the frame to its partner), of
        the running reference (the mean true inverse depth of the frames scored before,
        the frame's own for the first: a constant that knows the world so far), and of
        each of `others` ("abs_inv_<name>"; None is scored as the running reference)."""
        true_baseline = float(np.linalg.norm(true_translation))
        valid = np.isfinite(frame.depth) & (frame.depth > 0)
        truth = true_baseline / frame.depth[valid]
        if self._reference_count:
            reference = self._reference_sum / self._reference_count
        else:
            reference = float(truth.mean())
        self._reference_sum += float(truth.mean())
        self._reference_count += 1
        scores = {
            "abs_inv": float(np.mean(np.abs(truth - inv_depth[valid]))),
            "abs_inv_mean": float(np.mean(np.abs(truth - reference))),
            "true_baseline": true_baseline,
        }
        for name, other in others.items():
            predicted = reference if other is None else other[valid]
            scores[f"abs_inv_{name}"] = float(np.mean(np.abs(truth - predicted)))
        return scores

    # ----------------------------------------------------------------- updates

    def _placed(self, state: TrainState) -> TrainState:
        """`state` replicated on the updates' devices."""
        return jax.device_put(state, sharding.replicated(self._mesh))

    def _published(self) -> dict[str, Any]:
        """The state's variables on the prediction's device."""
        return jax.device_put(self._state.variables(), self._prediction_device)

    def _run_updates(self, state: TrainState, batches: list[dict]) -> TrainState:
        for index, batch in enumerate(batches):
            rng = jax.random.fold_in(jax.random.key(self.settings.seed), self.updates + index)
            batch = sharding.to_global_batch(batch, self._mesh, list(batch))
            state, _ = self._train_step(state, batch, rng)
        return jax.block_until_ready(state)

    def _join(self) -> None:
        """Swaps in the parameters of the update in flight, once it is done."""
        if self._pending is not None:
            self._state = self._pending.result()
            self._pending = None
            self.published = self._published()

    def _batches(self, count: int, newest: int) -> list[dict[str, np.ndarray]]:
        """`count` training batches from the buffer, only the keys the train step reads."""
        size, zoom = self.settings.batch_size, self.settings.zoom
        return [
            {
                key: value
                for key, value in self.buffer.batch(size, newest=newest, zoom=zoom).items()
                if key in self.keys
            }
            for _ in range(count)
        ]

    def _update(self) -> None:
        count = self.settings.updates_per_frame
        if not self.settings.learn or count == 0 or len(self.buffer) == 0:
            return
        batches = self._batches(count, newest=1)
        state = self._state
        if self._worker is None:
            self._state = self._run_updates(state, batches)
            self.published = self._published()
        else:
            self._pending = self._worker.submit(self._run_updates, state, batches)
        self.updates += count

    def train_offline(self, updates: int, chunk: int = 50) -> None:
        """`updates` steps on batches drawn uniformly from the whole buffer (no newest
        pair first): the offline reference's training on the pairs a stream gave."""
        self._join()
        for done in range(0, updates, chunk):
            batches = self._batches(min(chunk, updates - done), newest=0)
            self._state = self._run_updates(self._state, batches)
            self.updates += len(batches)
        self.published = self._published()

    # -------------------------------------------------------------------- API

    def observe(self, frame: Frame, predict: bool = True) -> dict[str, Any]:
        """Predicts `frame`'s depth, scores it (in simulation), then learns from it.

        `predict=False` only pairs the frame and stores its pair (the offline
        reference's collection: nothing predicted, scored or learned).

        Returns:
          {"frame", "partner" (its index, or None: no partner yet, nothing predicted),
          "baseline" (odometry, metres), "inv_depth" [H, W] (baselines), "latency_ms"
          (the frame in, the depth published: flow and network), "abs_inv",
          "abs_inv_mean" and "true_baseline" in simulation, "labelled", "updates" (so
          far), "update_wait_ms" (joining the update in flight)}.
        """
        if frame.index != self.next_frame:
            raise ValueError(f"frame {frame.index} arrived, the learner expects {self.next_frame}")
        start = time.perf_counter()
        result: dict[str, Any] = {"frame": frame.index, "partner": None}
        found = self._partner(frame)
        if found is not None:
            partner, _ = found
            example, baseline = self._pair(frame, partner)
            result.update(partner=partner.index, baseline=baseline)
            if predict:
                batch = {key: example[key][None] for key in self._model_keys}
                inv_depth = np.asarray(self._predict(self.published, batch)[0])
                result["inv_depth"] = inv_depth
                result["latency_ms"] = 1e3 * (time.perf_counter() - start)
                if frame.depth is not None:
                    true_rotation, true_translation = geometry.relative_pose(
                        frame.true_rotation,
                        frame.true_translation,
                        partner.true_rotation,
                        partner.true_translation,
                    )
                    others = {}
                    if self._references is not None:
                        others = self._references.predict(example, true_rotation, true_translation)
                    result.update(self._score(frame, inv_depth, true_translation, others))
            self._add_flow_pose(example)
            labels = self.labels_of(frame, baseline)
            if self._teacher.count:
                rng = np.random.default_rng([self.settings.seed, frame.index])
                taught = teacher.classical_labels(example, baseline, self._teacher, rng)
                labels = labels_lib.first_per_pixel(np.concatenate([labels, taught]))
            result["labelled"] = bool(len(labels))
            if len(labels) or self.self_supervised:
                vectors = {key: example[key] for key in VECTOR_FIELDS}
                self.buffer.add(
                    LabelledPair(frame.image, partner.image, example["flow"], labels, vectors)
                )
        joined = time.perf_counter()
        self._join()
        result["update_wait_ms"] = 1e3 * (time.perf_counter() - joined)
        if found is not None and predict:
            self._update()
        result["updates"] = self.updates
        self._window.append(frame)
        self._remember(frame)
        self.next_frame = frame.index + 1
        return result

    def resume_from(self, frame: Frame) -> None:
        """Puts a frame before `next_frame` back in the partner window (a resumed run
        replays the `max_partner_gap` frames before its position so)."""
        if frame.index >= self.next_frame:
            raise ValueError(f"frame {frame.index} is not before the position {self.next_frame}")
        self._window.append(frame)
        self._remember(frame)

    def finish(self) -> None:
        """Waits for the update in flight and swaps it in."""
        self._join()

    def state(self) -> dict[str, Any]:
        """Model and optimiser state, buffer, counters: what `restore` takes (the update
        in flight is joined first)."""
        self._join()
        return {
            "train_state": self._state,
            "buffer": self.buffer.state(),
            "counters": {
                "next_frame": self.next_frame,
                "updates": self.updates,
                "reference_sum": self._reference_sum,
                "reference_count": self._reference_count,
            },
        }

    def restore(self, state: dict[str, Any]) -> None:
        """Continues from `state()` (the partner window refilled by `resume_from`)."""
        self._join()
        self._state = self._placed(state["train_state"])
        self.published = self._published()
        self.buffer = ReplayBuffer.from_state(state["buffer"])
        counters = state["counters"]
        self.next_frame, self.updates = int(counters["next_frame"]), int(counters["updates"])
        self._reference_sum = float(counters["reference_sum"])
        self._reference_count = int(counters["reference_count"])
        self._window.clear()
        self._memory.clear()
