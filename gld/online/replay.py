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

    def batch(self, batch_size: int, newest: int = 1) -> dict[str, np.ndarray]:
        """A training batch of the example contract: the newest pair `newest` times
        (0 or 1), the rest drawn uniformly (with replacement) from the buffer.

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
        drawn = self._rng.integers(len(self), size=batch_size - newest)
        slots = np.concatenate([[self.newest] * newest, drawn]).astype(np.int64)
        arrays = self._arrays
        depth = np.zeros((batch_size, self.height, self.width), np.float32)
        mask = np.zeros((batch_size, self.height, self.width), bool)
        for index, slot in enumerate(slots):
            for row, column, value in arrays["labels"][slot, : arrays["label_count"][slot]]:
                depth[index, int(row), int(column)] = value
                mask[index, int(row), int(column)] = True
        batch = {
            "image1": arrays["image1"][slots].astype(np.float32) / 255.0 - 0.5,
            "image2": arrays["image2"][slots].astype(np.float32) / 255.0 - 0.5,
            "flow": arrays["flow"][slots],
            "depth": depth,
            "sparse_mask": mask,
            "depth_valid": mask,
        }
        batch.update({key: arrays[key][slots] for key in VECTOR_FIELDS})
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
