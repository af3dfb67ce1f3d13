"""Tests of gld/input_pipeline.py on tiny procedural two-view scenes."""

from __future__ import annotations

import collections
import json
import os
import pickle
import signal
import subprocess
import sys
import time
import types
from pathlib import Path

import numpy as np
import pytest
from conftest import REPO_ROOT

from gld import contract, geometry, input_pipeline, records

HEIGHT, WIDTH = 24, 32


def _render_view(
    camera_rotation: np.ndarray,
    camera_translation: np.ndarray,
    intrinsics: np.ndarray,
    texture_phase: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """Ray-casts a room corner (floor, back wall, left wall) with a smooth 3-D texture.

    The camera maps world points X to X_cam = R X + t. Returns the [H, W, 3] uint8 image
    and the [H, W] camera-z depth.
    """
    camera_matrix = geometry.intrinsics_matrix(intrinsics, HEIGHT, WIDTH)
    grid = geometry.pixel_grid(HEIGHT, WIDTH).astype(np.float64)
    rays_cam = (
        np.concatenate([grid, np.ones_like(grid[..., :1])], -1) @ np.linalg.inv(camera_matrix).T
    )
    origin = -camera_rotation.T @ camera_translation
    directions = rays_cam @ camera_rotation  # R^T d for every ray (row vectors)
    # Planes n . X = c: floor y = 1, back wall z = 4, left wall x = -2.5.
    planes = [(np.array([0.0, 1.0, 0.0]), 1.0), (np.array([0.0, 0.0, 1.0]), 4.0)]
    planes.append((np.array([1.0, 0.0, 0.0]), -2.5))
    distance = np.full((HEIGHT, WIDTH), np.inf)
    for normal, offset in planes:
        along = directions @ normal
        safe = np.where(np.abs(along) > 1e-9, along, 1e-9)
        hit = (offset - origin @ normal) / safe
        distance = np.where((hit > 0) & (hit < distance), hit, distance)
    points = origin + distance[..., None] * directions
    frequencies = 0.6 * np.array([[7.0, 5.0, 6.0], [4.0, 8.0, 5.5], [6.5, 4.5, 7.5]])
    colour = 0.5 + 0.4 * np.sin(points @ frequencies.T + texture_phase)
    image = np.clip(np.rint(colour * 255), 0, 255).astype(np.uint8)
    # Camera-space rays have z = 1, so the ray parameter is the camera-z depth.
    return image, distance.astype(np.float32)


def make_scene(seed: int) -> dict:
    """A raw example (the decoded record form of `gld.records`) with exact geometry."""
    rng = np.random.default_rng(seed)
    intrinsics1 = np.array([0.89, 1.19, 0.45, 0.55]) * rng.uniform(0.9, 1.1, 4)
    intrinsics2 = np.array([0.89, 1.19, 0.52, 0.47]) * rng.uniform(0.9, 1.1, 4)
    rotation = geometry.rotation_matrix(rng.normal(size=3) * 0.04)
    # Mostly sideways motion keeps the epipole out of the image (good parallax).
    translation = np.array([rng.choice([-1, 1]) * 0.3, rng.uniform(-0.1, 0.1), 0.1])
    translation *= rng.uniform(0.5, 2.0)
    phase = rng.uniform(0, 2 * np.pi, 3)
    image1, depth1 = _render_view(np.eye(3), np.zeros(3), intrinsics1, phase)
    image2, depth2 = _render_view(rotation, translation, intrinsics2, phase)
    gt_flow, gt_flow_valid = geometry.ground_truth_flow(
        depth1, depth2, intrinsics1, intrinsics2, rotation, translation
    )
    # A distinguishable "estimated" flow: ground truth plus a smooth known offset field.
    offset = np.stack(
        [np.linspace(0.0, 1.0, WIDTH)[None, :].repeat(HEIGHT, 0), np.full((HEIGHT, WIDTH), 0.5)],
        -1,
    )
    return {
        "image1": image1,
        "image2": image2,
        "depth1": depth1,
        "depth2": depth2,
        "intrinsics1": intrinsics1.astype(np.float32),
        "intrinsics2": intrinsics2.astype(np.float32),
        "rotation": rotation.astype(np.float32),
        "translation": translation.astype(np.float32),
        "flow": (gt_flow + offset).astype(np.float16),
        "gt_flow": gt_flow,
        "gt_flow_valid": gt_flow_valid,
        "id": f"scene-{seed:03d}",
    }


@pytest.fixture(scope="module")
def scenes() -> list[dict]:
    return [make_scene(seed) for seed in range(7)]


@pytest.fixture(scope="module")
def source(scenes) -> list[dict]:
    return [records.encode(scene) for scene in scenes]


def photometric_error(example: dict) -> float:
    """Mean |image1 - image2 warped by gt_flow| over valid, well-inside pixels."""
    grid = geometry.pixel_grid(*example["depth"].shape)
    warped, inside = geometry.sample_bilinear(example["image2"], grid + example["gt_flow"])
    mask = example["gt_flow_valid"] & inside
    assert mask.sum() > 0.1 * mask.size
    return float(np.abs(warped - example["image1"])[mask].mean())


def triangulation_error(example: dict) -> float:
    """Max relative error of depth triangulated from gt_flow with the example's pose."""
    size = example["depth"].shape
    camera1 = geometry.intrinsics_matrix(example["intrinsics1"].astype(np.float64), *size)
    camera2 = geometry.intrinsics_matrix(example["intrinsics2"].astype(np.float64), *size)
    depth = geometry.triangulate_depth(
        example["gt_flow"].astype(np.float64),
        camera1,
        camera2,
        example["rotation"].astype(np.float64),
        example["translation"].astype(np.float64),
    )
    mask = example["gt_flow_valid"] & example["depth_valid"]
    assert mask.sum() > 0.3 * mask.size
    return float(np.max(np.abs(depth[mask] - example["depth"][mask]) / example["depth"][mask]))


AUGMENTATIONS = {
    "none": lambda e: e,
    "rotate_180": contract.rotate_180,
    "mirror_x": contract.mirror_x,
    "rotate_then_mirror": lambda e: contract.mirror_x(contract.rotate_180(e)),
    "mirror_then_rotate": lambda e: contract.rotate_180(contract.mirror_x(e)),
}


def test_decode_example_follows_the_contract(source, scenes):
    example = contract.decode_example(source[0], where="test[0]")
    assert example["image1"].shape == (HEIGHT, WIDTH, 3)
    assert example["image1"].dtype == np.float32
    assert -0.5 <= example["image1"].min() and example["image1"].max() <= 0.5
    np.testing.assert_allclose(example["image2"], scenes[0]["image2"] / 255.0 - 0.5, atol=1e-6)
    assert example["flow"].shape == (HEIGHT, WIDTH, 2) and example["flow"].dtype == np.float32
    np.testing.assert_allclose(example["flow"], scenes[0]["flow"].astype(np.float32))
    assert example["depth"].dtype == np.float32 and example["depth_valid"].dtype == bool
    assert example["gt_flow_valid"].dtype == bool
    for key, shape in [("intrinsics1", (4,)), ("rotation", (3, 3)), ("translation", (3,))]:
        assert example[key].shape == shape and example[key].dtype == np.float32
    assert example["id"] == "scene-000"
    gt_example = contract.decode_example(source[0], flow_source="gt")
    np.testing.assert_array_equal(gt_example["flow"], scenes[0]["gt_flow"])


def test_decode_example_zeroes_invalid_depth(scenes):
    scene = dict(scenes[1])
    depth = scene["depth1"].copy()
    depth[0, 0], depth[1, 1], depth[2, 2] = np.nan, -1.0, np.inf
    scene["depth1"] = depth
    example = contract.decode_example(records.encode(scene))
    assert not example["depth_valid"][0, 0] and not example["depth_valid"][1, 1]
    assert not example["depth_valid"][2, 2] and example["depth_valid"][3, 3]
    assert example["depth"][0, 0] == 0 and example["depth"][1, 1] == 0
    assert np.all(np.isfinite(example["depth"]))


def test_decode_example_of_some_fields_reads_only_the_stored_fields_they_need(source):
    full = contract.decode_example(source[3])
    # The fields it does not read may be anything, as a source skipping them gives them.
    unread = dict(source[3], image1=b"not a png", gt_flow=b"zlib bytes", rotation="x")
    fields = ("depth", "translation", "flow")
    assert contract.stored_fields(fields) == ("depth1", "translation", "flow", "id")
    assert contract.stored_fields(fields, flow_source="gt") == (
        "depth1",
        "translation",
        "gt_flow",
        "id",
    )
    example = contract.decode_example(unread, fields=fields)
    assert sorted(example) == ["depth", "depth_valid", "flow", "id", "translation"]
    for key in example:
        np.testing.assert_array_equal(example[key], full[key], err_msg=key)
    with pytest.raises(ValueError, match=r"test\[3\]: rotation"):
        contract.decode_example(unread, fields=("rotation",), where="test[3]")
    with pytest.raises(ValueError, match="image1"):
        contract.decode_example(unread)


def test_an_evaluation_of_a_few_fields_skips_decoding_the_others(tiny_builder, monkeypatch):
    import zlib

    source = tiny_builder.as_data_source("test")
    skipping = records.decoding_only(source, ("depth1", "translation", "id"))
    assert isinstance(skipping[0]["gt_flow"], bytes)  # left zlib-compressed
    assert isinstance(skipping[0]["depth1"], np.ndarray)
    keys = ("depth", "depth_valid")
    every_field = [source[index] for index in range(len(source))]  # no TFDS source: all read
    # TFDS inflates each zlib field it decodes (depth1, depth2, flow, gt_flow); of a
    # record read for the depth alone, only depth1. No image is decoded.
    inflated = []
    decompress = zlib.decompress
    monkeypatch.setattr(zlib, "decompress", lambda *a: inflated.append(1) or decompress(*a))
    monkeypatch.setattr(records, "decode_png", lambda *a: pytest.fail("an image was decoded"))
    fitted = list(input_pipeline.eval_batches(source, batch_size=5, keys=keys))
    assert len(inflated) == 5 * input_pipeline.num_eval_batches(len(source), 5, 1)
    monkeypatch.undo()
    reference = list(input_pipeline.eval_batches(every_field, batch_size=5, keys=keys))
    assert len(fitted) == len(reference) == input_pipeline.num_eval_batches(len(source), 5, 1)
    for batch, expected in zip(fitted, reference, strict=True):
        assert sorted(batch) == sorted(expected) == ["depth", "depth_valid", "example_mask", "id"]
        for key in batch:
            np.testing.assert_array_equal(batch[key], expected[key], err_msg=key)


@pytest.mark.parametrize("name", list(AUGMENTATIONS))
def test_geometry_stays_consistent_under_augmentation(source, name):
    for index in (0, 3):
        example = AUGMENTATIONS[name](contract.decode_example(source[index]))
        assert photometric_error(example) < 0.03
        assert triangulation_error(example) < 1e-3
        rotation = example["rotation"].astype(np.float64)
        np.testing.assert_allclose(rotation.T @ rotation, np.eye(3), atol=1e-5)
        assert np.linalg.det(rotation) == pytest.approx(1.0, abs=1e-5)


def test_checks_catch_a_flow_sign_error(source):
    """Moving flow pixels without negating the vectors must fail both checks."""
    example = contract.decode_example(source[0])
    wrong = contract.rotate_180(example)
    wrong["gt_flow"] = -wrong["gt_flow"]
    assert photometric_error(wrong) > 0.06
    assert triangulation_error(wrong) > 0.1
    wrong_intrinsics = contract.mirror_x(example)
    wrong_intrinsics["intrinsics1"] = example["intrinsics1"]
    assert triangulation_error(wrong_intrinsics) > 1e-2


@pytest.mark.parametrize("name", ["rotate_180", "mirror_x", "rotate_then_mirror"])
def test_estimated_flow_is_transformed_like_gt_flow(source, scenes, name):
    example = contract.decode_example(source[2])
    offset = example["flow"] - example["gt_flow"]  # the known field added in make_scene
    augmented = AUGMENTATIONS[name](example)
    flipped_offset = AUGMENTATIONS[name]({"flow": offset, "gt_flow": offset, **_pose(example)})
    np.testing.assert_allclose(
        augmented["flow"] - augmented["gt_flow"], flipped_offset["flow"], atol=1e-6
    )
    # And its warp is as good as that of the ground truth up to the known offset.
    corrected = dict(augmented, gt_flow=augmented["flow"] - flipped_offset["flow"])
    assert photometric_error(corrected) < 0.03


def _pose(example: dict) -> dict:
    return {key: example[key] for key in ("intrinsics1", "intrinsics2", "rotation", "translation")}


def test_augmentations_move_pixels_and_invert_themselves(source):
    example = contract.decode_example(source[4])
    rotated = contract.rotate_180(example)
    mirrored = contract.mirror_x(example)
    v, u = 5, 7
    assert rotated["depth"][HEIGHT - 1 - v, WIDTH - 1 - u] == example["depth"][v, u]
    assert mirrored["depth"][v, WIDTH - 1 - u] == example["depth"][v, u]
    np.testing.assert_array_equal(mirrored["image1"][v, WIDTH - 1 - u], example["image1"][v, u])
    np.testing.assert_allclose(
        rotated["intrinsics2"][2:], 1.0 - example["intrinsics2"][2:], atol=1e-7
    )
    np.testing.assert_allclose(mirrored["intrinsics1"][3], example["intrinsics1"][3])
    for transform in (contract.rotate_180, contract.mirror_x):
        twice = transform(transform(example))
        for key, value in example.items():
            if key != "id":
                np.testing.assert_allclose(twice[key], value, atol=1e-6, err_msg=key)


def test_normalise_scale(source):
    example = contract.decode_example(source[5])
    norm = np.linalg.norm(example["translation"])
    assert abs(norm - 1) > 0.05  # the fixture's translations are not unit already
    normalised = contract.normalise_scale(example)
    assert np.linalg.norm(normalised["translation"]) == pytest.approx(1.0, abs=1e-6)
    np.testing.assert_allclose(normalised["depth"], example["depth"] / norm, rtol=1e-6)
    np.testing.assert_array_equal(normalised["depth"][~example["depth_valid"]], 0)
    # Scaling depth and translation together keeps the triangulation consistent.
    assert triangulation_error(normalised) < 1e-3
    example["translation"] = np.zeros(3, np.float32)
    with pytest.raises(ValueError, match="scene-005"):
        contract.normalise_scale(example)


@pytest.mark.parametrize("num_pixels", [1, 4, 16, 64])
def test_sparse_mask_picks_exactly_k_valid_pixels(num_pixels):
    depth_valid = np.random.default_rng(0).random((HEIGHT, WIDTH)) < 0.4
    mask = contract.sample_sparse_mask(depth_valid, num_pixels, np.random.default_rng(1))
    assert mask.shape == depth_valid.shape and mask.dtype == bool
    assert mask.sum() == num_pixels
    assert not np.any(mask & ~depth_valid)
    again = contract.sample_sparse_mask(depth_valid, num_pixels, np.random.default_rng(1))
    np.testing.assert_array_equal(mask, again)


def test_sparse_mask_dense_and_scarce():
    depth_valid = np.zeros((HEIGHT, WIDTH), bool)
    depth_valid[3, [4, 9, 20]] = True
    rng = np.random.default_rng(0)
    np.testing.assert_array_equal(contract.sample_sparse_mask(depth_valid, 16, rng), depth_valid)
    np.testing.assert_array_equal(contract.sample_sparse_mask(depth_valid, 0, rng), depth_valid)
    with pytest.raises(ValueError, match="-1"):
        contract.sample_sparse_mask(depth_valid, -1, rng)


def test_prepare_example_randomness_by_seed_id_and_epoch(source):
    def prepare(epoch, fixed=False, seed=3, index=0):
        return contract.prepare_example(
            source[index],
            epoch=epoch,
            seed=seed,
            gt_pixels=4,
            augment=True,
            fixed_sparse_pixels=fixed,
        )

    first = prepare(epoch=0)
    assert first["sparse_mask"].sum() == 4
    assert not np.any(first["sparse_mask"] & ~first["depth_valid"])
    assert np.linalg.norm(first["translation"]) == pytest.approx(1.0, abs=1e-6)
    np.testing.assert_array_equal(prepare(epoch=0)["sparse_mask"], first["sparse_mask"])
    np.testing.assert_array_equal(prepare(epoch=0)["image1"], first["image1"])
    # The masks are drawn in the augmented frame, so compare them in a canonical frame:
    # unaugmented examples share the depth_valid layout.
    masks = [
        contract.prepare_example(
            source[0], epoch=e, seed=3, gt_pixels=4, augment=False, fixed_sparse_pixels=fixed
        )["sparse_mask"]
        for fixed in (False, True)
        for e in range(3)
    ]
    assert not np.array_equal(masks[0], masks[1]) or not np.array_equal(masks[1], masks[2])
    np.testing.assert_array_equal(masks[3], masks[4])
    np.testing.assert_array_equal(masks[3], masks[5])
    # Over epochs the augmentation visits more than one of the four frames.
    frames = {tuple(np.round(prepare(epoch=e)["intrinsics1"][2:], 5)) for e in range(12)}
    assert len(frames) > 1
    # A different seed gives a different mask.
    other_seed = [prepare(epoch=0, seed=s)["sparse_mask"] for s in range(4, 8)]
    assert any(not np.array_equal(m, first["sparse_mask"]) for m in other_seed)


def _take(iterator, count: int) -> list[dict]:
    return [next(iterator) for _ in range(count)]


def _assert_same_batches(batches_a: list[dict], batches_b: list[dict]) -> None:
    assert len(batches_a) == len(batches_b)
    for batch_a, batch_b in zip(batches_a, batches_b, strict=True):
        assert batch_a.keys() == batch_b.keys()
        for key in batch_a:
            np.testing.assert_array_equal(batch_a[key], batch_b[key], err_msg=key)


def test_train_batches_follow_the_contract(source):
    dataset = input_pipeline.train_dataset(source, batch_size=3, seed=0, gt_pixels=16)
    batch = next(iter(dataset))
    expected = {
        "image1": ((3, HEIGHT, WIDTH, 3), np.float32),
        "image2": ((3, HEIGHT, WIDTH, 3), np.float32),
        "flow": ((3, HEIGHT, WIDTH, 2), np.float32),
        "depth": ((3, HEIGHT, WIDTH), np.float32),
        "depth_valid": ((3, HEIGHT, WIDTH), np.bool_),
        "sparse_mask": ((3, HEIGHT, WIDTH), np.bool_),
        "intrinsics1": ((3, 4), np.float32),
        "intrinsics2": ((3, 4), np.float32),
        "rotation": ((3, 3, 3), np.float32),
        "translation": ((3, 3), np.float32),
        "gt_flow": ((3, HEIGHT, WIDTH, 2), np.float32),
        "gt_flow_valid": ((3, HEIGHT, WIDTH), np.bool_),
    }
    for key, (shape, dtype) in expected.items():
        assert batch[key].shape == shape and batch[key].dtype == dtype, key
    source_ids = {f"scene-{i:03d}" for i in range(len(source))}
    assert batch["id"].shape == (3,) and len(set(batch["id"])) == 3
    assert set(batch["id"]) <= source_ids
    np.testing.assert_array_equal(batch["sparse_mask"].sum(axis=(1, 2)), [16, 16, 16])
    np.testing.assert_allclose(np.linalg.norm(batch["translation"], axis=-1), 1.0, atol=1e-6)


def test_process_shards_are_disjoint_and_cover_the_split(source):
    process_count = 3
    epochs = []
    for process_index in range(process_count):
        dataset = input_pipeline.train_dataset(
            source,
            batch_size=1,
            seed=5,
            gt_pixels=1,
            augment=False,
            process_index=process_index,
            process_count=process_count,
        )
        shard_size = len(range(len(source))[process_index::process_count])
        ids = [str(batch["id"][0]) for batch in _take(iter(dataset), 3 * shard_size)]
        # Each epoch is a permutation of the same shard.
        shard_epochs = [ids[e * shard_size : (e + 1) * shard_size] for e in range(3)]
        assert all(sorted(e) == sorted(shard_epochs[0]) for e in shard_epochs)
        assert len(set(shard_epochs[0])) == shard_size
        epochs.append(set(shard_epochs[0]))
    assert sum(len(shard) for shard in epochs) == len(source)
    assert set.union(*epochs) == {f"scene-{i:03d}" for i in range(len(source))}


def test_shuffle_depends_on_seed_and_epoch(source):
    def order(seed, count):
        dataset = input_pipeline.train_dataset(
            source, batch_size=1, seed=seed, gt_pixels=1, augment=False
        )
        return [str(batch["id"][0]) for batch in _take(iter(dataset), count)]

    orders = order(0, 4 * len(source))
    epochs = [tuple(orders[e * len(source) : (e + 1) * len(source)]) for e in range(4)]
    assert len(set(epochs)) > 1
    assert order(0, len(source)) == list(epochs[0])
    assert any(order(seed, len(source)) != list(epochs[0]) for seed in (1, 2))


def _train_iterator(source, worker_count: int):
    return iter(
        input_pipeline.train_dataset(
            source, batch_size=2, seed=7, gt_pixels=4, worker_count=worker_count
        )
    )


@pytest.mark.parametrize(("saved_with", "resumed_with"), [(0, 0), (1, 1), (0, 2), (2, 0)])
def test_iterator_state_restores_the_same_batches(source, saved_with, resumed_with):
    iterator = _train_iterator(source, saved_with)
    _take(iterator, 3)  # into the second epoch of 7 records
    state = json.loads(json.dumps(iterator.get_state()))
    expected = _take(iterator, 5)
    restored = _train_iterator(source, resumed_with)
    restored.set_state(state)
    actual = _take(restored, 5)
    _assert_same_batches(expected, actual)
    # The restore matters: a fresh iterator starts elsewhere.
    fresh = _train_iterator(source, 0)
    fresh_ids = [list(batch["id"]) for batch in _take(fresh, 5)]
    assert fresh_ids != [list(batch["id"]) for batch in expected]
    for each in (iterator, restored, fresh):
        each.close()


def test_every_worker_count_reads_the_same_batches(source):
    """Batch k is examples 2k and 2k + 1 of the one stream, whoever prepares them."""
    stream = _train_iterator(source, 0)
    expected = _take(stream, 6)
    stream.close()
    for worker_count in (1, 3):
        workers = _train_iterator(source, worker_count)
        _assert_same_batches(expected, _take(workers, 6))
        workers.close()


class _CountingSource:
    """A list of records that counts the reads of each index."""

    def __init__(self, records):
        self.records, self.reads = records, collections.Counter()

    def __len__(self):
        return len(self.records)

    def __getitem__(self, index):
        self.reads[index] += 1
        # A fresh copy, as a data source decodes a new record at every read.
        return {
            key: np.array(value) if isinstance(value, np.ndarray) else value
            for key, value in self.records[index].items()
        }


def _epochs_of_batches(source, epochs: int) -> list[dict]:
    iterator = iter(input_pipeline.train_dataset(source, batch_size=1, seed=3, gt_pixels=4))
    batches = _take(iterator, epochs * len(source))
    iterator.close()
    return batches


@pytest.mark.parametrize("budget", ["all", "some", "none"])
def test_kept_records_are_read_once_and_give_the_same_batches(source, monkeypatch, budget):
    # Kept records are kept decoded.
    sizes = [input_pipeline._record_bytes(records.decode(record)) for record in source]
    monkeypatch.setattr(input_pipeline, "_RECORD_CACHE_BYTES", 0)
    expected = _epochs_of_batches(_CountingSource(source), 3)
    cache_bytes = {"all": sum(sizes), "some": 3 * min(sizes), "none": 0}[budget]
    monkeypatch.setattr(input_pipeline, "_RECORD_CACHE_BYTES", cache_bytes)
    counting = _CountingSource(source)
    _assert_same_batches(expected, _epochs_of_batches(counting, 3))
    # A kept record is read once; the others in every epoch (some once more, by the
    # prefetch into the fourth). The kept ones fit the budget.
    kept = [index for index in range(len(source)) if counting.reads[index] == 1]
    assert all(counting.reads[index] >= 3 for index in range(len(source)) if index not in kept)
    assert sum(sizes[index] for index in kept) <= cache_bytes
    expected_kept = {"all": [len(source)], "some": [1, 2, 3], "none": [0]}[budget]
    assert len(kept) in expected_kept


def test_a_kept_record_cannot_be_written(source):
    reader = input_pipeline._RecordReader(_CountingSource(source), cache_bytes=1 << 30)
    record, _ = reader.read(0)
    assert reader.read(0)[0] is record
    with pytest.raises(ValueError, match="read-only"):
        record["depth1"][0, 0] = 1.0
    with pytest.raises(ValueError, match="read-only"):
        record["image1"][0, 0] = 0  # kept decoded, as an array
    # A grain worker's copy keeps nothing of what this process read.
    copy = pickle.loads(pickle.dumps(reader))
    assert copy._cache == {} and copy.cache_bytes == reader.cache_bytes


def test_states_of_earlier_checkpoints_are_read(source):
    # One process batching in order: its examples read are a multiple of the batch.
    iterator = _train_iterator(source, 0)
    iterator.set_state({"next_index": 6})
    _assert_same_batches(_take(_train_iterator(source, 0), 5)[3:], _take(iterator, 2))
    iterator.close()
    # Workers that batched their own shares: the batches read, with a warning.
    saved_by_workers = {
        "next_index_in_cycle": 1,
        "iterators_in_use_states": [{"next_index": 4}, {"next_index": 2}],
        "exhausted": [0, 0],
    }
    iterator = _train_iterator(source, 0)
    with pytest.warns(UserWarning, match="saved with 2 workers"):
        iterator.set_state(saved_by_workers)
    assert iterator.get_state() == {"next_batch": 3}
    for bad in ({"next_index": 5}, {"next_batch": -1}, {"something": 1}):
        with pytest.raises(ValueError, match="state"):
            iterator.set_state(bad)


@pytest.mark.parametrize("process_count", [1, 2, 3])
def test_eval_batches_cover_every_example_once(source, process_count):
    batch_size = 2
    expected_batches = input_pipeline.num_eval_batches(len(source), batch_size, process_count)
    real_ids = []
    padded_rows = 0
    for process_index in range(process_count):
        batches = list(
            input_pipeline.eval_batches(
                source,
                batch_size=batch_size,
                process_index=process_index,
                process_count=process_count,
            )
        )
        assert len(batches) == expected_batches
        # Padding rows are copies of the shard's first record (record process_index).
        padding_id = f"scene-{process_index:03d}"
        for batch in batches:
            assert batch["image1"].shape[0] == batch_size
            assert batch["example_mask"].dtype == np.bool_
            np.testing.assert_array_equal(batch["sparse_mask"], batch["depth_valid"])
            real_ids += [str(i) for i in batch["id"][batch["example_mask"]]]
            padded = ~batch["example_mask"]
            assert [str(i) for i in batch["id"][padded]] == [padding_id] * int(padded.sum())
            for row in np.flatnonzero(padded):
                np.testing.assert_array_equal(batch["image1"][row], batches[0]["image1"][0])
            padded_rows += int(padded.sum())
        # Unaugmented: the first real example equals the decoded record, scale-normalised.
        first = batches[0]
        reference = contract.normalise_scale(contract.decode_example(source[process_index]))
        np.testing.assert_array_equal(first["image1"][0], reference["image1"])
        np.testing.assert_allclose(first["depth"][0], reference["depth"])
    assert sorted(real_ids) == sorted(f"scene-{i:03d}" for i in range(len(source)))
    # Every process yields the same number of rows: whatever is not real is padding.
    assert padded_rows == expected_batches * batch_size * process_count - len(source)


def test_num_eval_batches():
    assert input_pipeline.num_eval_batches(7, 2, 1) == 4
    assert input_pipeline.num_eval_batches(7, 2, 3) == 2
    assert input_pipeline.num_eval_batches(8, 4, 2) == 1


def test_corrupt_record_names_file_and_index(source):
    corrupt = list(source)
    corrupt[4] = dict(source[4], image2=b"not a png")
    with pytest.raises(ValueError, match=r"record 4 .*image2"):
        list(input_pipeline.eval_batches(corrupt, batch_size=7))
    with pytest.raises(ValueError, match=r"record 4"):
        train_iterator = iter(
            input_pipeline.train_dataset(corrupt, batch_size=1, seed=0, gt_pixels=1)
        )
        _take(train_iterator, len(corrupt))
    corrupt[4] = dict(source[4], gt_flow=np.full((HEIGHT, WIDTH, 2), np.nan, np.float32))
    with pytest.raises(ValueError, match=r"record 4 .*gt_flow"):
        list(input_pipeline.eval_batches(corrupt, batch_size=7))
    corrupt[4] = dict(source[4], depth1=np.zeros((HEIGHT, WIDTH + 1), np.float32))
    with pytest.raises(ValueError, match=r"record 4 .*depth1.*shape"):
        list(input_pipeline.eval_batches(corrupt, batch_size=7))


class _TfdsLikeSource:
    """A source with TFDS's metadata: two files of 3 and 4 records."""

    split = "train"

    def __init__(self, records_list):
        self.records_list = records_list
        files = [
            types.SimpleNamespace(
                filename="gld_scenes-train.array_record-00000-of-00002",
                skip=0,
                take=3,
                examples_in_shard=3,
            ),
            types.SimpleNamespace(
                filename="gld_scenes-train.array_record-00001-of-00002",
                skip=0,
                take=-1,
                examples_in_shard=4,
            ),
        ]
        split_info = types.SimpleNamespace(file_instructions=files)
        self.dataset_info = types.SimpleNamespace(splits={"train": split_info})

    def __len__(self):
        return len(self.records_list)

    def __getitem__(self, index):
        record = self.records_list[index]
        if record is None:
            raise OSError("checksum mismatch")
        return record


def test_corrupt_record_in_a_tfds_source_names_the_file(source):
    corrupt = list(source)
    corrupt[5] = None
    with pytest.raises(ValueError, match=r"00001-of-00002, record 2 .*checksum"):
        list(input_pipeline.eval_batches(_TfdsLikeSource(corrupt), batch_size=7))


def test_bad_arguments_are_rejected(source):
    with pytest.raises(ValueError, match="flow_source"):
        input_pipeline.train_dataset(source, batch_size=1, seed=0, gt_pixels=1, flow_source="dis")
    with pytest.raises(ValueError, match="process_index"):
        input_pipeline.train_dataset(
            source, batch_size=1, seed=0, gt_pixels=1, process_index=2, process_count=2
        )
    with pytest.raises(ValueError, match="empty"):
        list(input_pipeline.eval_batches([], batch_size=1))


# ------------------------------------------------------- integration with gld_scenes/tiny


@pytest.fixture(scope="module")
def tiny_builder(tmp_path_factory):
    data = pytest.importorskip("data")
    return data.prepare("gld_scenes/tiny", tmp_path_factory.mktemp("datasets"))


def _flow_error(example: dict) -> float:
    """Mean end-point error of the estimated flow against gt_flow on valid pixels."""
    difference = np.linalg.norm(example["flow"] - example["gt_flow"], axis=-1)
    return float(difference[example["gt_flow_valid"]].mean())


def test_gld_scenes_geometry_survives_every_augmentation(tiny_builder):
    source = tiny_builder.as_data_source("train")
    for index in range(4):
        example = contract.decode_example(source[index], where=f"train[{index}]")
        reference_photometric = photometric_error(example)
        reference_flow_error = _flow_error(example)
        assert reference_photometric < 0.03
        for name, augmentation in AUGMENTATIONS.items():
            augmented = augmentation(example)
            # Flips permute pixels exactly, so every check is unchanged, not merely small.
            assert photometric_error(augmented) == pytest.approx(reference_photometric, abs=1e-4)
            assert triangulation_error(augmented) < 1e-3, name
            assert _flow_error(augmented) == pytest.approx(reference_flow_error, rel=1e-4), name
        # Moving the estimated flow without transforming its vectors would be caught.
        unrotated_vectors = dict(rotated := contract.rotate_180(example))
        unrotated_vectors["flow"] = -rotated["flow"]
        assert _flow_error(unrotated_vectors) > 1.5 * reference_flow_error


def test_gld_scenes_train_and_eval(tiny_builder):
    train = tiny_builder.as_data_source("train", decoders=input_pipeline.source_decoders())
    assert isinstance(train[0]["depth2"], bytes)  # left compressed
    ids_by_process = []
    for process_index in range(2):
        iterator = iter(
            input_pipeline.train_dataset(
                train,
                batch_size=4,
                seed=1,
                gt_pixels=64,
                process_index=process_index,
                process_count=2,
            )
        )
        batches = _take(iterator, len(train) // 2 // 4)  # one epoch of this shard
        batch = batches[0]
        assert batch["image1"].shape == (4, 48, 64, 3) and batch["flow"].shape == (4, 48, 64, 2)
        np.testing.assert_array_equal(batch["sparse_mask"].sum(axis=(1, 2)), 64)
        assert not np.any(batch["sparse_mask"] & ~batch["depth_valid"])
        ids_by_process.append({str(i) for b in batches for i in b["id"]})
    assert len(ids_by_process[0]) == len(ids_by_process[1]) == len(train) // 2
    assert not ids_by_process[0] & ids_by_process[1]

    test = tiny_builder.as_data_source("test")
    batches = list(input_pipeline.eval_batches(test, batch_size=5))
    assert len(batches) == input_pipeline.num_eval_batches(len(test), 5, 1) == 4
    real = [str(i) for b in batches for i in b["id"][b["example_mask"]]]
    assert len(real) == len(set(real)) == len(test)
    assert batches[-1]["example_mask"].tolist() == [True] + [False] * 4


class _CorruptingSource:
    """A TFDS data source whose record `bad_index` has an unreadable image."""

    def __init__(self, source, bad_index: int):
        self.source, self.bad_index = source, bad_index
        self.dataset_info, self.split = source.dataset_info, source.split

    def __len__(self):
        return len(self.source)

    def __getitem__(self, index):
        record = self.source[index]
        return dict(record, image1=b"\x89PNG broken") if index == self.bad_index else record


def test_gld_scenes_corrupt_record_names_file_and_index(tiny_builder):
    source = _CorruptingSource(tiny_builder.as_data_source("test"), bad_index=6)
    with pytest.raises(
        ValueError, match=r"gld_scenes-test\.array_record-00000-of-00001, record 6 .*image1"
    ):
        list(input_pipeline.eval_batches(source, batch_size=4))


_ORPHAN_SCRIPT = """
import multiprocessing, sys, time

def child(worker_init):
    worker_init(0, 1)
    print("watching", flush=True)
    time.sleep(120)

if __name__ == "__main__":
    from gld import input_pipeline
    # Made in the parent, as the training stream makes it for grain's workers.
    worker_init = input_pipeline.ExitWithParent(period=0.1)
    process = multiprocessing.get_context("spawn").Process(target=child, args=(worker_init,))
    process.start()
    print(process.pid, flush=True)
    time.sleep(120)
"""


def _alive(pid: int) -> bool:
    """Whether `pid` runs: a process that has exited, is exiting (its /proc entry goes
    between the open and the read) or is a zombie waiting to be reaped is not alive."""
    try:
        state = Path(f"/proc/{pid}/status").read_text()
    except (FileNotFoundError, ProcessLookupError):
        return False
    fields = next((line.split() for line in state.splitlines() if line.startswith("State:")), [])
    return len(fields) > 1 and fields[1] != "Z"


@pytest.mark.skipif(not Path("/proc").is_dir(), reason="reads /proc")
def test_a_worker_ends_when_its_parent_is_killed(tmp_path):
    script = tmp_path / "parent.py"
    script.write_text(_ORPHAN_SCRIPT)
    env = dict(os.environ, PYTHONPATH=str(REPO_ROOT), JAX_PLATFORMS="cpu")
    parent = subprocess.Popen(
        [sys.executable, str(script)], stdout=subprocess.PIPE, text=True, env=env, cwd=REPO_ROOT
    )
    child_pid = int(parent.stdout.readline())
    assert parent.stdout.readline().strip() == "watching"
    assert _alive(child_pid)
    parent.send_signal(signal.SIGKILL)  # no clean-up runs in the parent
    parent.wait()
    deadline = time.monotonic() + 30
    while _alive(child_pid) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert not _alive(child_pid)


def test_a_worker_started_after_its_parent_died_exits():
    """The parent's pid is handed to the worker: one read in the worker after the parent
    died would be the pid of the process that adopted it."""
    code = (
        "import os, sys, time\n"
        "from gld import input_pipeline\n"
        "input_pipeline.ExitWithParent(parent=int(sys.argv[1]), period=0.1)(0, 1)\n"
        "time.sleep(60)\n"
    )
    gone = subprocess.run(
        [sys.executable, "-c", "import os; print(os.getpid())"],
        capture_output=True,
        text=True,
        check=True,
    )
    dead_parent = int(gone.stdout)
    env = dict(os.environ, PYTHONPATH=str(REPO_ROOT), JAX_PLATFORMS="cpu")
    worker = subprocess.run(
        [sys.executable, "-c", code, str(dead_parent)], env=env, cwd=REPO_ROOT, timeout=50
    )
    assert worker.returncode == 1


def test_the_pose_from_the_flow_is_estimated_once_and_flipped_with_the_example(source):
    keys = ("flow", "flow_rotation", "flow_translation", "rotation", "translation")
    flipped_kinds = set()
    for epoch in range(6):
        example = contract.prepare_example(
            source[2], epoch=epoch, seed=1, gt_pixels=1, flow_source="gt", keys=keys
        )
        # Exact flow: the essential matrix's pose is the true one, in the augmented frame.
        rotation_error = geometry.rotation_error_degrees(
            example["flow_rotation"], example["rotation"]
        )
        translation_error = geometry.translation_error_degrees(
            example["flow_translation"], example["translation"]
        )
        assert rotation_error < 0.5 and translation_error < 2.0, epoch
        flipped_kinds.add(float(np.sign(example["translation"][0])))
    assert flipped_kinds == {-1.0, 1.0}  # some epochs mirrored the sideways motion
    # Not made unless asked for.
    plain = contract.prepare_example(source[2], epoch=0, seed=1, gt_pixels=1)
    assert "flow_rotation" not in plain
