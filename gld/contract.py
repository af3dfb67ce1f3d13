"""The example contract: one stored record -> one example, in numpy.

    example = prepare_example(record, epoch=0, seed=0, gt_pixels=1)

`decode_example` reads a record into the contract's fields (`CONTRACT_KEYS`: `image1`,
`image2`, `flow`, `depth`, `depth_valid`, `intrinsics1`, `intrinsics2`, `rotation`,
`translation`, `gt_flow`, `gt_flow_valid`, `id`, and on request the pose the essential
matrix gets from the input flow, `DERIVED_KEYS`), checking shapes and values; then
augmentation (rotate 180 degrees with p = 0.5, then mirror along x with p = 0.5, the
cameras and the pose kept consistent), scale normalisation (||t|| = 1) and the sparse
supervised pixels (`sample_sparse_mask`). Randomness is explicit: numpy `Generator`s
seeded by (seed, stable hash of the example id, epoch) on independent streams
(`example_rng`), so an example gets the same treatment whatever the shard, shuffle or
worker count. `gld.input_pipeline` runs these over a record source with grain.
"""

from __future__ import annotations

import hashlib
from collections.abc import Collection, Sequence
from typing import Any

import cv2
import numpy as np

from gld import flow_pose, geometry, records

FLOW_SOURCES = ("estimated", "gt")


# The fields of an example (the example contract of the design notes).
CONTRACT_KEYS = (
    "image1",
    "image2",
    "flow",
    "depth",
    "depth_valid",
    "sparse_mask",
    "intrinsics1",
    "intrinsics2",
    "rotation",
    "translation",
    "gt_flow",
    "gt_flow_valid",
    "flow_rotation",
    "flow_translation",
    "id",
)


# Fields derived from others, made only when a consumer names them in `keys`: the
# relative pose the essential matrix gets from the input flow (`gld.flow_pose`).
DERIVED_KEYS = flow_pose.FLOW_POSE_KEYS


# Stored fields no example of the contract is made from.
UNUSED_RECORD_KEYS = ("depth2",)


# Maps with the image's spatial layout; vector fields are listed separately.
_SPATIAL_KEYS = ("image1", "image2", "depth", "depth_valid", "gt_flow_valid", "sparse_mask")


_FLOW_KEYS = ("flow", "gt_flow")


# Stream ids of the per-example random generators.
_AUGMENT_STREAM = 0


_SPARSE_STREAM = 1


# Translations shorter than this cannot set the scale of a pair.
_MIN_TRANSLATION_NORM = 1e-6


def _check_shape(value: np.ndarray, shape: tuple[int, ...], key: str, where: str) -> None:
    if value.shape != shape:
        raise ValueError(f"{where}: {key} has shape {value.shape}, expected {shape}")


def _check_finite(value: np.ndarray, key: str, where: str) -> None:
    if not np.all(np.isfinite(value)):
        raise ValueError(f"{where}: {key} contains non-finite values")


# The stored fields each field of the contract is decoded from ("flow" comes from the one
# the flow source names).
_STORED_FIELDS = {
    "image1": ("image1",),
    "image2": ("image2",),
    "depth": ("depth1",),
    "depth_valid": ("depth1",),
    "intrinsics1": ("intrinsics1",),
    "intrinsics2": ("intrinsics2",),
    "rotation": ("rotation",),
    "translation": ("translation",),
    "gt_flow": ("gt_flow",),
    "gt_flow_valid": ("gt_flow_valid",),
    "id": ("id",),
}


def stored_fields(fields: Collection[str], flow_source: str = "estimated") -> tuple[str, ...]:
    """The record keys `decode_example` reads to make the contract's `fields` (and
    `depth1`, which every example has): the other stored fields a source may skip."""
    stored = {"depth1", "id"}
    for field in fields:
        if field == "flow":
            stored.add("flow" if flow_source == "estimated" else "gt_flow")
        else:
            stored.update(_STORED_FIELDS.get(field, ()))
    return tuple(key for key in records.RECORD_KEYS if key in stored)


def decode_example(
    record: dict[str, Any],
    *,
    flow_source: str = "estimated",
    where: str = "",
    decoded: bool = False,
    fields: Collection[str] | None = None,
) -> dict[str, Any]:
    """A stored record -> an example before scale normalisation and sparse sampling:
    `records.decode`, then the checks of the contract and its names and ranges.

    Args:
      record: a record as read from a data source (see `gld.records`).
      flow_source: "estimated" takes the network's input flow from the stored
        estimated flow, "gt" from the ground-truth flow.
      where: names the record (file and index) in errors.
      decoded: `record` is `records.decode`'s output already (a reader that keeps the
        records decoded), not a data source's.
      fields: the contract's fields to make (`depth` and `depth_valid` always); only
        the stored fields they come from (`stored_fields`) are decoded and checked, so
        the source may skip the others. None makes all of them.

    Returns:
      image1, image2: [H, W, 3] float32 in [-0.5, 0.5]; flow: [H, W, 2] float32 pixels,
      I1 -> I2; depth: [H, W] float32 view-1 depth, 0 where invalid; depth_valid: [H, W]
      bool; intrinsics1, intrinsics2: [4] float32 normalised; rotation: [3, 3];
      translation: [3] (raw scale); gt_flow: [H, W, 2] float32; gt_flow_valid: [H, W]
      bool; id: str (those of `fields`, when given).

    Raises:
      ValueError: naming `where` for missing keys, undecodable images, inconsistent
        shapes, non-finite flow/intrinsics/pose or a rotation that is not orthonormal.
    """
    if flow_source not in FLOW_SOURCES:
        raise ValueError(f"unknown flow_source {flow_source!r}; valid: {FLOW_SOURCES}")
    where = where or "record"
    read = set(records.RECORD_KEYS) if fields is None else set(stored_fields(fields, flow_source))
    raw = record if decoded else records.decode(record, where=where, keys=read)
    height, width = raw["image1" if "image1" in read else "depth1"].shape[:2]
    spatial = (
        ("image2", (height, width, 3)),
        ("depth1", (height, width)),
        ("gt_flow", (height, width, 2)),
        ("flow", (height, width, 2)),
        ("gt_flow_valid", (height, width)),
    )
    for key, shape in spatial:
        if key in read:
            _check_shape(raw[key], shape, key, where)
    for key in ("intrinsics1", "intrinsics2"):
        if key in read:
            _check_shape(raw[key], (4,), key, where)
            _check_finite(raw[key], key, where)
            if np.any(raw[key][:2] <= 0):
                raise ValueError(
                    f"{where}: {key} has non-positive focal lengths {raw[key].tolist()}"
                )
    for key, shape in (("rotation", (3, 3)), ("translation", (3,))):
        if key in read:
            _check_shape(raw[key], shape, key, where)
    for key in ("rotation", "translation", "flow", "gt_flow"):
        if key in read:
            _check_finite(raw[key], key, where)
    if "rotation" in read:
        rotation = raw["rotation"]
        if np.abs(rotation.T @ rotation - np.eye(3)).max() > 1e-3:
            raise ValueError(f"{where}: rotation is not orthonormal: {rotation.tolist()}")

    depth = raw["depth1"]
    depth_valid = geometry.valid_depth(depth)
    made = {
        "image1": lambda: raw["image1"].astype(np.float32) / 255.0 - 0.5,
        "image2": lambda: raw["image2"].astype(np.float32) / 255.0 - 0.5,
        "flow": lambda: raw["flow"] if flow_source == "estimated" else raw["gt_flow"].copy(),
        "depth": lambda: np.where(depth_valid, depth, 0.0).astype(np.float32),
        "depth_valid": lambda: depth_valid,
        "intrinsics1": lambda: raw["intrinsics1"],
        "intrinsics2": lambda: raw["intrinsics2"],
        "rotation": lambda: raw["rotation"],
        "translation": lambda: raw["translation"],
        "gt_flow": lambda: raw["gt_flow"],
        "gt_flow_valid": lambda: raw["gt_flow_valid"],
        "id": lambda: raw["id"],
    }
    wanted = made.keys() if fields is None else {*fields, "depth", "depth_valid", "id"}
    return {key: make() for key, make in made.items() if key in wanted}


def _flip_frame(example: dict[str, Any], axes: tuple[int, ...]) -> dict[str, Any]:
    """Flips the image along `axes` (0 = v, 1 = u) and keeps the geometry consistent.

    Flipping pixel axis u maps u -> W - 1 - u, the normalised principal point
    cx/W -> 1 - cx/W and the camera frame's x axis -> -x (likewise v, cy, y). With
    the frame change S = diag(+-1, +-1, 1) applied to both cameras, X2 = R X1 + t
    becomes S X2 = (S R S)(S X1) + S t; flow vectors change sign along flipped axes.
    """
    flipped = dict(example)
    frame_signs = np.ones(3, np.float32)
    for axis in axes:
        frame_signs[1 - axis] = -1.0  # pixel axis 0 (v) is camera y, axis 1 (u) is camera x
    # OpenCV's flip codes: 0 flips rows (v), 1 columns (u), -1 both; it is several times
    # faster than copying a negatively strided numpy view.
    flip_code = -1 if len(axes) == 2 else axes[0]
    for key in _SPATIAL_KEYS + _FLOW_KEYS:
        if key not in example:
            continue
        value = np.asarray(example[key])
        if value.dtype == np.bool_:
            flipped[key] = cv2.flip(value.view(np.uint8), flip_code).view(np.bool_)
        else:
            flipped[key] = cv2.flip(value, flip_code)
    for key in _FLOW_KEYS:
        if key in example:
            for axis in axes:
                flipped[key][..., 1 - axis] *= -1.0  # flow channel 0 is u, 1 is v
    for key in ("intrinsics1", "intrinsics2"):
        if key not in example:
            continue
        intrinsics = np.array(example[key], np.float32)
        for axis in axes:
            principal_index = 3 - axis  # cx/W at index 2 (axis 1), cy/H at index 3 (axis 0)
            intrinsics[principal_index] = 1.0 - intrinsics[principal_index]
        flipped[key] = intrinsics
    flip = np.diag(frame_signs)
    for rotation_key, translation_key in (("rotation", "translation"), DERIVED_KEYS):
        if rotation_key in example:
            flipped[rotation_key] = (flip @ example[rotation_key] @ flip).astype(np.float32)
        if translation_key in example:
            flipped[translation_key] = (frame_signs * example[translation_key]).astype(np.float32)
    return flipped


def rotate_180(example: dict[str, Any]) -> dict[str, Any]:
    """Rotates an example by 180 degrees: images, maps, flow vectors, intrinsics and pose.

    u -> W - 1 - u, v -> H - 1 - v, (cx/W, cy/H) -> (1 - cx/W, 1 - cy/H), flow -> -flow,
    R -> S R S and t -> S t with S = diag(-1, -1, 1).
    """
    return _flip_frame(example, (0, 1))


def mirror_x(example: dict[str, Any]) -> dict[str, Any]:
    """Mirrors an example along x: u -> W - 1 - u, cx/W -> 1 - cx/W, flow_u -> -flow_u,
    R -> M R M and t -> M t with M = diag(-1, 1, 1)."""
    return _flip_frame(example, (1,))


def normalise_scale(example: dict[str, Any]) -> dict[str, Any]:
    """Scales depth and translation so that ||translation|| = 1 (flow is scale-free).

    Raises:
      ValueError: naming the example id when the translation is (nearly) zero, since
        such a pair carries no depth scale.
    """
    translation = np.asarray(example["translation"], np.float64)
    norm = float(np.linalg.norm(translation))
    if not np.isfinite(norm) or norm < _MIN_TRANSLATION_NORM:
        raise ValueError(
            f"example {example.get('id')!r}: translation {translation.tolist()} has norm "
            f"{norm:.3g}; depth cannot be normalised by it"
        )
    normalised = dict(example)
    normalised["translation"] = (translation / norm).astype(np.float32)
    normalised["depth"] = (np.asarray(example["depth"], np.float64) / norm).astype(np.float32)
    return normalised


def sample_sparse_mask(
    depth_valid: np.ndarray, num_pixels: int, rng: np.random.Generator
) -> np.ndarray:
    """Chooses the supervised pixels among the valid ones.

    Args:
      depth_valid: [H, W] bool.
      num_pixels: k >= 0; 0 means dense supervision (every valid pixel).
      rng: the generator the pixels are drawn from.

    Returns:
      [H, W] bool with exactly k True pixels, all valid (all valid pixels if fewer
      than k exist).
    """
    if num_pixels < 0:
        raise ValueError(f"num_pixels must be >= 0 (0 = dense), got {num_pixels}")
    depth_valid = np.asarray(depth_valid, bool)
    valid_indices = np.flatnonzero(depth_valid)
    if num_pixels == 0 or num_pixels >= valid_indices.size:
        return depth_valid.copy()
    chosen = rng.choice(valid_indices, size=num_pixels, replace=False)
    mask = np.zeros(depth_valid.size, bool)
    mask[chosen] = True
    return mask.reshape(depth_valid.shape)


def stable_id_hash(example_id: str) -> int:
    """A 64-bit hash of an example id that is the same in every process and run."""
    return int.from_bytes(hashlib.blake2b(example_id.encode(), digest_size=8).digest(), "little")


def example_rng(seed: int, example_id: str, epoch: int, stream: int) -> np.random.Generator:
    """The generator of one example, epoch and stream (augmentation or sparse sampling)."""
    sequence = np.random.SeedSequence(
        entropy=[seed, stable_id_hash(example_id), epoch], spawn_key=(stream,)
    )
    return np.random.default_rng(sequence)


def needed_fields(keys: Collection[str]) -> set[str]:
    """The contract's fields `prepare_example` decodes to give a consumer `keys`: those,
    the depth, its validity and the translation (the scale normalisation and the sparse
    pixels read them), and what the derived keys are made from.

    Raises:
      ValueError: a key that is no field of the contract.
    """
    unknown = sorted(set(keys) - set(CONTRACT_KEYS))
    if unknown:
        raise ValueError(f"unknown example keys {unknown}; valid: {CONTRACT_KEYS}")
    needed = {*keys, "id", "depth", "depth_valid", "translation"}
    if set(keys) & set(DERIVED_KEYS):
        needed |= {"flow", "intrinsics1", "intrinsics2"}
    return needed


def prepare_example(
    record: dict[str, Any],
    *,
    epoch: int,
    seed: int,
    gt_pixels: int,
    flow_source: str = "estimated",
    augment: bool = True,
    fixed_sparse_pixels: bool = False,
    keys: Sequence[str] | None = None,
    where: str = "",
    decoded: bool = False,
) -> dict[str, Any]:
    """A stored record -> one example of the contract: decode, augment, normalise, sparsify.

    Args:
      record: a record from a data source.
      epoch: how many times this process has gone through its shard before.
      seed: the run's data seed.
      gt_pixels: supervised pixels per example (0 = dense).
      flow_source: "estimated" or "gt" (see `decode_example`).
      augment: rotate 180 degrees (p = 0.5), then mirror along x (p = 0.5).
      fixed_sparse_pixels: draw the same supervised pixels in every epoch (the epoch is
        dropped from their seed), as for a robot that measured each frame once.
      keys: the contract's fields the consumer reads ("id" is always kept); only the
        stored fields they need are decoded (`needed_fields`, `decode_example`), and
        the others are dropped before augmentation and batching. None keeps all the
        stored ones. `DERIVED_KEYS` are made only when named here: the pose from
        the input flow is estimated before augmentation (once per pair and process,
        `gld.flow_pose.pose_of_example`) and flipped with the example.
      where: names the record in errors.
      decoded: `record` is `records.decode`'s output already (see `decode_example`).

    Returns:
      the example dict of the contract, with `sparse_mask` [H, W] bool.
    """
    fields = None if keys is None else needed_fields(keys)
    example = decode_example(
        record, flow_source=flow_source, where=where, decoded=decoded, fields=fields
    )
    if keys is not None and set(keys) & set(DERIVED_KEYS):
        rotation, translation, _ = flow_pose.pose_of_example(
            example["flow"], example["intrinsics1"], example["intrinsics2"]
        )
        example["flow_rotation"], example["flow_translation"] = rotation, translation
    if augment:
        augment_rng = example_rng(seed, example["id"], epoch, _AUGMENT_STREAM)
        do_rotate, do_mirror = augment_rng.random(2) < 0.5
        if do_rotate:
            example = rotate_180(example)
        if do_mirror:
            example = mirror_x(example)
    example = normalise_scale(example)
    sparse_epoch = 0 if fixed_sparse_pixels else epoch
    sparse_rng = example_rng(seed, example["id"], sparse_epoch, _SPARSE_STREAM)
    example["sparse_mask"] = sample_sparse_mask(example["depth_valid"], gt_pixels, sparse_rng)
    if keys is not None:
        example = {key: example[key] for key in ("id", *keys) if key in example}
    return example
