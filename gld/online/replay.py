"""A bounded replay buffer of labelled pairs, sampled reproducibly.

    buffer = ReplayBuffer(capacity=256, height=96, width=128, seed=0)
    buffer.add(pair)                       # a labelled pair (`LabelledPair`)
    batch = buffer.batch(8, newest=1)      # the newest pair and 7 drawn from the buffer
    state = buffer.state()                 # arrays and generator state: a checkpoint's
    buffer = ReplayBuffer.from_state(state)

The buffer keeps a uniform sample of every pair it was given (reservoir sampling,
Vitter's algorithm R): once full, the n-th pair replaces a random slot with probability
capacity / n. Old worlds stay represented however long the stream, and memory is fixed
at `capacity` pairs, allocated once. A pair is stored compactly (images uint8, the
labelled pixels as (row, column, depth) triples) and expanded into the example contract's
fields (`gld.contract`) only in a batch. Every random choice comes from one numpy
generator whose state is part of `state()`, so a restored buffer samples what the
original would have.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import cv2
import numpy as np

# The example contract's vector fields a pair carries besides the images and flow.
VECTOR_FIELDS = {
    "intrinsics1": (4,),
    "intrinsics2": (4,),
    "rotation": (3, 3),
    "translation": (3,),
    "flow_rotation": (3, 3),
    "flow_translation": (3,),
}


@dataclasses.dataclass(frozen=True)
class LabelledPair:
    """One pair with its range reading(s), as the learner stores it.

    Attributes:
      image1, image2: [H, W, 3] uint8; the depth is view 1's.
      flow: [H, W, 2] float32 pixels, image1 -> image2.
      labels: [N, 3] float32 (row, column, depth in baselines) of the labelled pixels
        (none for the self-supervised loss, which reads no depth).
      vectors: the `VECTOR_FIELDS` (cameras, the odometry's pose with ||t|| = 1, the
        essential matrix's pose from the flow), float32.
    """

    image1: np.ndarray
    image2: np.ndarray
    flow: np.ndarray
    labels: np.ndarray
    vectors: dict[str, np.ndarray]


class ReplayBuffer:
    """A fixed-capacity reservoir of labelled pairs (see the module docstring)."""

    def __init__(self, capacity: int, height: int, width: int, seed: int, max_labels: int = 1):
        if capacity < 1:
            raise ValueError(f"capacity must be >= 1, got {capacity}")
        if max_labels < 1:
            raise ValueError(f"max_labels must be >= 1, got {max_labels}")
        self.capacity, self.height, self.width = capacity, height, width
        self.max_labels = max_labels
        self._rng = np.random.default_rng(seed)
        self.seen = 0  # pairs ever added
        self.newest = -1  # the slot of the newest pair
        size = (capacity, height, width)
        self._arrays = {
            "image1": np.zeros((*size, 3), np.uint8),
            "image2": np.zeros((*size, 3), np.uint8),
            "flow": np.zeros((*size, 2), np.float32),
            "labels": np.zeros((capacity, max_labels, 3), np.float32),
            "label_count": np.zeros(capacity, np.int32),
            **{
                key: np.zeros((capacity, *shape), np.float32)
                for key, shape in VECTOR_FIELDS.items()
            },
        }

    def __len__(self) -> int:
        return min(self.seen, self.capacity)

    @property
    def nbytes(self) -> int:
        """The buffer's memory, fixed at construction."""
        return sum(array.nbytes for array in self._arrays.values())

    def add(self, pair: LabelledPair) -> int | None:
        """Stores `pair`; its slot, or None when the reservoir passed it over."""
        labels = np.asarray(pair.labels, np.float32).reshape(-1, 3)
        if len(labels) > self.max_labels:
            raise ValueError(f"a pair holds 0 to {self.max_labels} labels, got {len(labels)}")
        if pair.image1.shape != (self.height, self.width, 3):
            raise ValueError(
                f"image1 has shape {pair.image1.shape}, the buffer holds "
                f"{self.height}x{self.width} pairs"
            )
        self.seen += 1
        if self.seen <= self.capacity:
            slot = self.seen - 1
        else:
            drawn = int(self._rng.integers(self.seen))
            if drawn >= self.capacity:
                return None
            slot = drawn
        arrays = self._arrays
        arrays["image1"][slot], arrays["image2"][slot] = pair.image1, pair.image2
        arrays["flow"][slot] = pair.flow
        arrays["labels"][slot] = 0.0
        arrays["labels"][slot, : len(labels)] = labels
        arrays["label_count"][slot] = len(labels)
        for key in VECTOR_FIELDS:
            arrays[key][slot] = pair.vectors[key]
        self.newest = slot
        return slot

    def _zoom(self, example: dict[str, np.ndarray], smallest: float) -> dict[str, np.ndarray]:
        """A random crop of a pair, at least `smallest` of each side, holding its first
        label, resized back (the flow and the cameras with it, depth unchanged)."""
        height, width = self.height, self.width
        side = self._rng.uniform(smallest, 1.0)
        crop_height, crop_width = max(1, round(height * side)), max(1, round(width * side))
        labels = example["labels"]
        row, column = (int(labels[0, 0]), int(labels[0, 1])) if len(labels) else (0, 0)
        low_top, high_top = (max(0, row - crop_height + 1), min(row, height - crop_height))
        low_left, high_left = (max(0, column - crop_width + 1), min(column, width - crop_width))
        if not len(labels):
            low_top, high_top, low_left, high_left = 0, height - crop_height, 0, width - crop_width
        top = int(self._rng.integers(low_top, high_top + 1))
        left = int(self._rng.integers(low_left, high_left + 1))
        scale_y, scale_x = height / crop_height, width / crop_width

        def resized(image):
            crop = image[top : top + crop_height, left : left + crop_width]
            return cv2.resize(crop, (width, height), interpolation=cv2.INTER_LINEAR)

        zoomed = dict(example)
        for key in ("image1", "image2"):
            zoomed[key] = resized(example[key])
        zoomed["flow"] = resized(example["flow"]) * np.float32([scale_x, scale_y])
        moved = labels.copy()
        # The pixel holding each labelled pixel's centre after the crop and resize.
        moved[:, 0] = np.floor((labels[:, 0] - top + 0.5) * scale_y)
        moved[:, 1] = np.floor((labels[:, 1] - left + 0.5) * scale_x)
        inside = (
            (moved[:, 0] >= 0) & (moved[:, 0] < height) & (moved[:, 1] >= 0) & (moved[:, 1] < width)
        )
        zoomed["labels"] = moved[inside]
        for key in ("intrinsics1", "intrinsics2"):
            fx, fy, cx, cy = example[key]
            zoomed[key] = np.float32(
                [
                    fx * width / crop_width,
                    fy * height / crop_height,
                    (cx * width - left) / crop_width,
                    (cy * height - top) / crop_height,
                ]
            )
        return zoomed

    def batch(self, batch_size: int, newest: int = 1, zoom: float = 1.0) -> dict[str, np.ndarray]:
        """A training batch of the example contract: the newest pair `newest` times
        (0 or 1), the rest drawn uniformly (with replacement) from the buffer.

        With `zoom` < 1, each pair is a random crop of at least that fraction of each
        side, holding its labelled pixel, resized back to the full size: a range sensor
        that reads one fixed pixel then labels pixels all over the image (the crop is a
        camera of longer focal length: the flow and the intrinsics scale with it, the
        camera-z depth does not change).

        Returns:
          image1, image2 [B, H, W, 3] float32 in [-0.5, 0.5]; flow; depth [B, H, W]
          (baselines at the labelled pixels, 0 elsewhere); sparse_mask and depth_valid
          [B, H, W] (the labelled pixels); the `VECTOR_FIELDS`.
        """
        if len(self) == 0:
            raise ValueError("the buffer is empty")
        if newest not in (0, 1) or batch_size < 1:
            raise ValueError(
                f"need batch_size >= 1 and newest in (0, 1), got {batch_size}, {newest}"
            )
        if not 0 < zoom <= 1:
            raise ValueError(f"zoom must be in (0, 1], got {zoom}")
        drawn = self._rng.integers(len(self), size=batch_size - newest)
        slots = np.concatenate([[self.newest] * newest, drawn]).astype(np.int64)
        arrays = self._arrays
        examples = []
        for slot in slots:
            example = {
                key: arrays[key][slot] for key in ("image1", "image2", "flow", *VECTOR_FIELDS)
            }
            example["labels"] = arrays["labels"][slot, : arrays["label_count"][slot]]
            examples.append(self._zoom(example, zoom) if zoom < 1 else example)
        depth = np.zeros((batch_size, self.height, self.width), np.float32)
        mask = np.zeros((batch_size, self.height, self.width), bool)
        for index, example in enumerate(examples):
            for row, column, value in example["labels"]:
                depth[index, int(row), int(column)] = value
                mask[index, int(row), int(column)] = True
        batch = {
            key: np.stack([example[key] for example in examples]).astype(np.float32) / 255.0 - 0.5
            for key in ("image1", "image2")
        }
        batch.update(
            {
                key: np.stack([example[key] for example in examples])
                for key in ("flow", *VECTOR_FIELDS)
            }
        )
        batch.update(depth=depth, sparse_mask=mask, depth_valid=mask)
        return batch

    def state(self) -> dict[str, Any]:
        """Everything to restore the buffer exactly: its arrays and counters, and the
        generator's state (JSON-ready) under "generator"."""
        return {
            "arrays": {key: array.copy() for key, array in self._arrays.items()},
            "settings": {
                "capacity": self.capacity,
                "height": self.height,
                "width": self.width,
                "max_labels": self.max_labels,
                "seen": self.seen,
                "newest": self.newest,
            },
            "generator": self._rng.bit_generator.state,
        }

    @classmethod
    def from_state(cls, state: dict[str, Any]) -> ReplayBuffer:
        """The buffer `state()` described."""
        settings = state["settings"]
        buffer = cls(
            settings["capacity"], settings["height"], settings["width"], 0, settings["max_labels"]
        )
        for key, array in state["arrays"].items():
            if buffer._arrays[key].shape != np.shape(array):
                raise ValueError(
                    f"stored buffer field {key} has shape {np.shape(array)}, expected "
                    f"{buffer._arrays[key].shape}"
                )
            buffer._arrays[key][...] = array
        buffer.seen, buffer.newest = int(settings["seen"]), int(settings["newest"])
        buffer._rng.bit_generator.state = state["generator"]
        return buffer
