"""The replay buffer (gld/online/replay.py): bounded, uniform over the stream, reproducible."""

import numpy as np
import pytest

from gld.online.replay import VECTOR_FIELDS, LabelledPair, ReplayBuffer

HEIGHT, WIDTH = 6, 8


def _pair(index: int) -> LabelledPair:
    """A pair whose images and label carry its index."""
    image = np.full((HEIGHT, WIDTH, 3), index % 256, np.uint8)
    vectors = {key: np.full(shape, index, np.float32) for key, shape in VECTOR_FIELDS.items()}
    labels = np.array([[index % HEIGHT, (index * 3) % WIDTH, 1.0 + index]], np.float32)
    return LabelledPair(
        image, image, np.full((HEIGHT, WIDTH, 2), index, np.float32), labels, vectors
    )


def test_memory_is_fixed_and_the_buffer_holds_a_uniform_sample():
    buffer = ReplayBuffer(capacity=100, height=HEIGHT, width=WIDTH, seed=0)
    size = buffer.nbytes
    for index in range(2000):
        buffer.add(_pair(index))
    assert len(buffer) == 100 and buffer.seen == 2000 and buffer.nbytes == size
    stored = buffer.state()["arrays"]["translation"][:, 0]
    # Reservoir sampling: a uniform sample of 0..1999 (mean 1000, sd of the mean ~58).
    assert abs(stored.mean() - 999.5) < 200
    assert stored.min() < 400 and stored.max() > 1600


def test_a_batch_holds_the_newest_pair_and_its_label_at_its_pixel():
    buffer = ReplayBuffer(capacity=4, height=HEIGHT, width=WIDTH, seed=1)
    for index in range(3):
        buffer.add(_pair(index))
    batch = buffer.batch(5, newest=1)
    assert batch["image1"].shape == (5, HEIGHT, WIDTH, 3)
    np.testing.assert_allclose(batch["image1"][0], 2 / 255.0 - 0.5, rtol=1e-6)
    assert batch["sparse_mask"][0].sum() == 1 and batch["sparse_mask"][0, 2, 6]
    assert batch["depth"][0, 2, 6] == pytest.approx(3.0) and batch["depth"][
        0
    ].sum() == pytest.approx(3.0)
    # The drawn pairs come from the buffer's three, each with its own label.
    drawn = batch["translation"][1:, 0].astype(int)
    assert set(drawn) <= {0, 1, 2}
    for row, index in enumerate(drawn, start=1):
        assert batch["depth"][row, index % HEIGHT, (index * 3) % WIDTH] == pytest.approx(
            1.0 + index
        )


def test_sampling_is_reproducible_and_survives_a_checkpoint():
    first = ReplayBuffer(capacity=8, height=HEIGHT, width=WIDTH, seed=3)
    second = ReplayBuffer(capacity=8, height=HEIGHT, width=WIDTH, seed=3)
    for index in range(20):
        assert first.add(_pair(index)) == second.add(_pair(index))
    restored = ReplayBuffer.from_state(first.state())
    for _ in range(3):
        expected = first.batch(4)
        for other in (second, restored):
            got = other.batch(4)
            for key in expected:
                np.testing.assert_array_equal(got[key], expected[key])
    # And the reservoir's choices after the checkpoint agree too.
    assert [first.add(_pair(i)) for i in range(20, 40)] == [
        restored.add(_pair(i)) for i in range(20, 40)
    ]
    other_seed = ReplayBuffer(capacity=8, height=HEIGHT, width=WIDTH, seed=4)
    for index in range(20):
        other_seed.add(_pair(index))
    assert not np.array_equal(other_seed.batch(4)["flow"], second.batch(4)["flow"])


def test_bad_use_is_refused():
    with pytest.raises(ValueError, match="capacity must be >= 1"):
        ReplayBuffer(capacity=0, height=HEIGHT, width=WIDTH, seed=0)
    buffer = ReplayBuffer(capacity=2, height=HEIGHT, width=WIDTH, seed=0)
    with pytest.raises(ValueError, match="the buffer is empty"):
        buffer.batch(2)
    pair = _pair(0)
    with pytest.raises(ValueError, match="holds 0 to 1 labels, got 2"):
        buffer.add(
            LabelledPair(pair.image1, pair.image2, pair.flow, np.zeros((2, 3)), pair.vectors)
        )
    with pytest.raises(ValueError, match="the buffer holds 6x8 pairs"):
        buffer.add(LabelledPair(pair.image1[:4], pair.image2, pair.flow, pair.labels, pair.vectors))


def test_a_zoomed_pair_labels_another_pixel_with_the_same_geometry():
    height, width = 24, 32
    buffer = ReplayBuffer(capacity=2, height=height, width=width, seed=5)
    vectors = {key: np.zeros(shape, np.float32) for key, shape in VECTOR_FIELDS.items()}
    camera = np.float32([0.9, 1.2, 0.5, 0.5])
    vectors.update(intrinsics1=camera, intrinsics2=camera)
    image = np.zeros((height, width, 3), np.uint8)
    flow = np.broadcast_to(np.float32([1.5, -2.0]), (height, width, 2)).copy()
    labels = np.float32([[10, 20, 3.0]])
    buffer.add(LabelledPair(image, image, flow, labels, vectors))

    def ray(row, column, intrinsics):
        fx, fy, cx, cy = intrinsics * np.float32([width, height, width, height])
        return np.array([(column - (cx - 0.5)) / fx, (row - (cy - 0.5)) / fy])

    before = ray(10, 20, camera)
    positions = set()
    for _ in range(20):
        batch = buffer.batch(1, newest=1, zoom=0.5)
        ((row, column),) = np.argwhere(batch["sparse_mask"][0])
        positions.add((row, column))
        assert batch["depth"][0, row, column] == pytest.approx(3.0)  # camera-z depth kept
        scale = batch["flow"][0, 0, 0, 0] / 1.5
        assert 1.0 <= scale <= 2.1
        np.testing.assert_allclose(batch["flow"][0, ..., 1], -2.0 * scale, rtol=0.05)
        intrinsics = batch["intrinsics1"][0]
        np.testing.assert_array_equal(intrinsics, batch["intrinsics2"][0])
        # The labelled pixel still looks along the same ray, within half a new pixel.
        after = ray(row, column, intrinsics)
        pixel = 1.0 / (intrinsics[0] * width)
        assert np.all(
            np.abs(after - before) <= 0.5 * pixel * np.float32([1, width / height]) + 1e-4
        )
    assert len(positions) > 5  # the one fixed pixel labels many
