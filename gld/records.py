"""The stored record of one two-view example, shared by every gld dataset builder.

Records are written by the TFDS builders in `data/` (array_record shards, no
TensorFlow: images are PNG bytes encoded by OpenCV, float maps are zlib-compressed
tensors) and decoded by `gld.input_pipeline`. Stored values are *raw*: metric depth
and the unnormalised translation; scale normalisation (||t|| = 1) happens in the
pipeline so the same records serve every protocol.

| key | stored as | decoded |
|---|---|---|
| image1, image2 | PNG bytes (RGB) | [H, W, 3] uint8 |
| depth1, depth2 | [H, W] float32 (zlib) | camera-z depth, 0 where invalid |
| intrinsics1, intrinsics2 | [4] float32 | normalised [fx/W, fy/H, cx/W, cy/H] |
| rotation, translation | [3, 3], [3] float32 | X2 = R X1 + t (raw scale) |
| flow | [H, W, 2] float16 (zlib) | estimated flow I1 -> I2, pixels |
| gt_flow | [H, W, 2] float32 (zlib) | flow from depth and pose |
| gt_flow_valid | [H, W] bool | inside view 2, in front, not occluded |
| id | text | stable example id |
"""

from __future__ import annotations

import dataclasses
from collections.abc import Collection, Sequence
from typing import Any

import cv2
import numpy as np
import tensorflow_datasets as tfds

IMAGE_KEYS = ("image1", "image2")
# The decoded dtype of every array a consumer reads (depth2, which the input pipeline
# skips, is left as the source gives it).
DECODED_DTYPES = {
    "depth1": np.float32,
    "intrinsics1": np.float32,
    "intrinsics2": np.float32,
    "rotation": np.float32,
    "translation": np.float32,
    "flow": np.float32,
    "gt_flow": np.float32,
    "gt_flow_valid": np.bool_,
}
RECORD_KEYS = (
    "image1",
    "image2",
    "depth1",
    "depth2",
    "intrinsics1",
    "intrinsics2",
    "rotation",
    "translation",
    "flow",
    "gt_flow",
    "gt_flow_valid",
    "id",
)


def features(height: int, width: int) -> tfds.features.FeaturesDict:
    """The TFDS feature spec of a record at a given resolution."""
    zlib = tfds.features.Encoding.ZLIB
    return tfds.features.FeaturesDict(
        {
            "image1": tfds.features.Tensor(shape=(), dtype=np.object_),
            "image2": tfds.features.Tensor(shape=(), dtype=np.object_),
            "depth1": tfds.features.Tensor(shape=(height, width), dtype=np.float32, encoding=zlib),
            "depth2": tfds.features.Tensor(shape=(height, width), dtype=np.float32, encoding=zlib),
            "intrinsics1": tfds.features.Tensor(shape=(4,), dtype=np.float32),
            "intrinsics2": tfds.features.Tensor(shape=(4,), dtype=np.float32),
            "rotation": tfds.features.Tensor(shape=(3, 3), dtype=np.float32),
            "translation": tfds.features.Tensor(shape=(3,), dtype=np.float32),
            "flow": tfds.features.Tensor(shape=(height, width, 2), dtype=np.float16, encoding=zlib),
            "gt_flow": tfds.features.Tensor(
                shape=(height, width, 2), dtype=np.float32, encoding=zlib
            ),
            "gt_flow_valid": tfds.features.Tensor(shape=(height, width), dtype=np.bool_),
            "id": tfds.features.Text(),
        }
    )


def encode_png(image: np.ndarray) -> bytes:
    """[H, W, 3] uint8 RGB -> PNG bytes."""
    if image.dtype != np.uint8 or image.ndim != 3 or image.shape[-1] != 3:
        raise ValueError(f"expected an [H, W, 3] uint8 image, got {image.shape} {image.dtype}")
    ok, encoded = cv2.imencode(".png", cv2.cvtColor(image, cv2.COLOR_RGB2BGR))
    if not ok:
        raise ValueError("OpenCV could not encode the image as PNG")
    return encoded.tobytes()


def decode_png(data: bytes, where: str = "image") -> np.ndarray:
    """PNG bytes -> [H, W, 3] uint8 RGB; a corrupt buffer raises ValueError naming `where`."""
    image = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)
    if image is None:
        raise ValueError(f"corrupt image data in {where}")
    return cv2.cvtColor(image, cv2.COLOR_BGR2RGB)


def encode(example: dict[str, Any]) -> dict[str, Any]:
    """A raw example (numpy, decoded form above) -> the values TFDS stores."""
    missing = [key for key in RECORD_KEYS if key not in example]
    if missing:
        raise ValueError(f"record is missing keys {missing}")
    record = {key: example[key] for key in RECORD_KEYS}
    for key in IMAGE_KEYS:
        record[key] = encode_png(np.asarray(example[key]))
    for key in ("depth1", "depth2", "gt_flow", "intrinsics1", "intrinsics2"):
        record[key] = np.asarray(example[key], np.float32)
    record["rotation"] = np.asarray(example["rotation"], np.float32)
    record["translation"] = np.asarray(example["translation"], np.float32)
    record["flow"] = np.asarray(example["flow"], np.float16)
    record["gt_flow_valid"] = np.asarray(example["gt_flow_valid"], bool)
    record["id"] = str(example["id"])
    return record


def decode(
    record: dict[str, Any], where: str = "record", keys: Collection[str] | None = None
) -> dict[str, Any]:
    """A record read from a TFDS data source -> numpy arrays (decoded form above): the
    one place stored values are decoded (images from PNG, arrays to `DECODED_DTYPES`).

    `where` names the record (file and index) in the error raised for corrupt data.
    `keys`: the stored fields to decode ("id" always), the others left out, which the
    source may then skip (`tfds.decode.SkipDecoding`); None decodes all of them.
    """
    if keys is not None and not set(keys) <= set(RECORD_KEYS):
        raise ValueError(f"unknown record keys {sorted(set(keys) - set(RECORD_KEYS))}")
    wanted = RECORD_KEYS if keys is None else [key for key in RECORD_KEYS if key in {*keys, "id"}]
    try:
        example = {key: record[key] for key in wanted}
    except KeyError as error:
        raise ValueError(f"{where}: missing key {error}") from None
    for key in IMAGE_KEYS:
        if key in example:
            example[key] = decode_png(record[key], f"{where}/{key}")
    for key, dtype in DECODED_DTYPES.items():
        if key not in example:
            continue
        try:
            example[key] = np.asarray(record[key], dtype)
        except (TypeError, ValueError) as error:
            raise ValueError(f"{where}: {key} is undecodable ({error})") from None
    example["id"] = record["id"].decode() if isinstance(record["id"], bytes) else str(record["id"])
    return example


def decoding_only(source: Sequence[Any], stored: Collection[str]) -> Sequence[Any]:
    """`source` decoding only the `stored` fields of its records: a TFDS data source is
    opened again with `tfds.decode.SkipDecoding` for the others (their zlib inflation is
    most of a record's read), any other source is given as it is. For a consumer of a
    few fields (`gld.contract.stored_fields`), as the dataset mean, which reads the depth
    alone: 1.4 ms a record of gld_scenes/small instead of 3.0, and no PNG decoding."""
    if not (dataclasses.is_dataclass(source) and hasattr(source, "decoders")):
        return source
    skipped = {key: tfds.decode.SkipDecoding() for key in RECORD_KEYS if key not in stored}
    return dataclasses.replace(source, decoders={**(source.decoders or {}), **skipped})
