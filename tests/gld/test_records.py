"""Tests of gld/records.py: the stored form of an example, through TFDS's serialisation."""

import numpy as np
import pytest

from gld import records

HEIGHT, WIDTH = 4, 6


def _example(seed=0) -> dict:
    """A raw example in the decoded form, with float32 values a float16 cannot hold."""
    rng = np.random.default_rng(seed)
    return {
        "image1": rng.integers(0, 256, (HEIGHT, WIDTH, 3), dtype=np.uint8),
        "image2": rng.integers(0, 256, (HEIGHT, WIDTH, 3), dtype=np.uint8),
        "depth1": rng.uniform(1.0, 5.0, (HEIGHT, WIDTH)).astype(np.float32),
        "depth2": np.where(rng.uniform(size=(HEIGHT, WIDTH)) < 0.3, 0.0, 2.5).astype(np.float32),
        "intrinsics1": np.array([0.9, 1.2, 0.5, 0.5]),
        "intrinsics2": np.array([0.95, 1.15, 0.48, 0.52]),
        "rotation": np.eye(3),
        "translation": np.array([0.3, -0.1, 2.0]),
        "flow": rng.normal(scale=3.0, size=(HEIGHT, WIDTH, 2)).astype(np.float32),
        "gt_flow": rng.normal(scale=3.0, size=(HEIGHT, WIDTH, 2)).astype(np.float32),
        "gt_flow_valid": rng.uniform(size=(HEIGHT, WIDTH)) < 0.5,
        "id": "scene-007/pair-3",
    }


def _store_and_read(example: dict) -> dict:
    """encode -> TFDS serialisation (what the array_record shards hold) -> decode."""
    features = records.features(HEIGHT, WIDTH)
    stored = features.deserialize_example_np(features.serialize_example(records.encode(example)))
    return records.decode(stored, where="test[0]")


def test_a_stored_record_decodes_to_the_example():
    example = _example()
    decoded = _store_and_read(example)
    assert list(decoded) == list(records.RECORD_KEYS)
    for key in ("image1", "image2", "depth1", "depth2", "gt_flow", "gt_flow_valid"):
        assert decoded[key].dtype == example[key].dtype, key
        np.testing.assert_array_equal(decoded[key], example[key], err_msg=key)
    for key in ("intrinsics1", "intrinsics2", "rotation", "translation"):
        assert decoded[key].dtype == np.float32, key
        np.testing.assert_array_equal(decoded[key], example[key].astype(np.float32), err_msg=key)
    assert decoded["id"] == "scene-007/pair-3" and isinstance(decoded["id"], str)
    # The estimated flow is stored as float16 and comes back as float32.
    assert decoded["flow"].dtype == np.float32
    np.testing.assert_array_equal(decoded["flow"], example["flow"].astype(np.float16))
    assert not np.array_equal(decoded["flow"], example["flow"])  # the rounding is real
    np.testing.assert_allclose(decoded["flow"], example["flow"], rtol=1e-3)


def test_a_float16_flow_round_trips_exactly_and_twice_is_once():
    example = _example(seed=1)
    example["flow"] = example["flow"].astype(np.float16).astype(np.float32)
    decoded = _store_and_read(example)
    np.testing.assert_array_equal(decoded["flow"], example["flow"])
    again = _store_and_read(decoded)
    for key in records.RECORD_KEYS:
        np.testing.assert_array_equal(again[key], decoded[key], err_msg=key)


def test_the_feature_spec_has_one_entry_per_record_key_with_the_documented_types():
    features = records.features(HEIGHT, WIDTH)
    assert set(features.keys()) == set(records.RECORD_KEYS)
    expected = {
        "depth1": ((HEIGHT, WIDTH), np.float32),
        "depth2": ((HEIGHT, WIDTH), np.float32),
        "intrinsics1": ((4,), np.float32),
        "intrinsics2": ((4,), np.float32),
        "rotation": ((3, 3), np.float32),
        "translation": ((3,), np.float32),
        "flow": ((HEIGHT, WIDTH, 2), np.float16),
        "gt_flow": ((HEIGHT, WIDTH, 2), np.float32),
        "gt_flow_valid": ((HEIGHT, WIDTH), np.bool_),
    }
    for key, (shape, dtype) in expected.items():
        assert features[key].shape == shape, key
        assert features[key].np_dtype == dtype, key


def test_png_round_trip_keeps_rgb_channel_order():
    image = np.zeros((2, 3, 3), np.uint8)
    image[..., 0] = 200  # pure red: a BGR/RGB swap would make it blue
    image[1, 2] = [1, 2, 3]
    data = records.encode_png(image)
    assert data[:8] == b"\x89PNG\r\n\x1a\n"
    np.testing.assert_array_equal(records.decode_png(data), image)


@pytest.mark.parametrize(
    "image",
    [np.zeros((2, 3, 3), np.float32), np.zeros((2, 3), np.uint8), np.zeros((2, 3, 4), np.uint8)],
)
def test_encode_png_rejects_what_is_not_an_rgb_uint8_image(image):
    with pytest.raises(ValueError, match=r"expected an \[H, W, 3\] uint8 image"):
        records.encode_png(image)


def test_an_example_missing_keys_is_refused_naming_them():
    example = _example()
    del example["depth2"], example["gt_flow_valid"]
    with pytest.raises(ValueError, match=r"missing keys \['depth2', 'gt_flow_valid'\]"):
        records.encode(example)


def test_a_field_of_the_wrong_shape_is_refused_naming_the_field():
    encoded = records.encode(dict(_example(), depth1=np.ones((HEIGHT, WIDTH + 1), np.float32)))
    with pytest.raises(ValueError, match=r'"depth1"(.|\n)*\(4, 7\) does not match \(4, 6\)'):
        records.features(HEIGHT, WIDTH).serialize_example(encoded)


def test_a_corrupt_record_names_the_record_and_the_field():
    features = records.features(HEIGHT, WIDTH)
    stored = features.deserialize_example_np(features.serialize_example(records.encode(_example())))
    with pytest.raises(ValueError, match=r"corrupt image data in shard-2\[5\]/image2"):
        records.decode(dict(stored, image2=b"\x89PNG broken"), where="shard-2[5]")
    missing = {key: value for key, value in stored.items() if key != "gt_flow"}
    with pytest.raises(ValueError, match=r"shard-2\[5\]: missing key 'gt_flow'"):
        records.decode(missing, where="shard-2[5]")
    with pytest.raises(ValueError, match=r"shard-2\[5\]: translation is undecodable"):
        records.decode(dict(stored, translation=["a", "b", "c"]), where="shard-2[5]")


def test_a_record_decodes_only_the_fields_asked_for_and_leaves_the_others_unread():
    features = records.features(HEIGHT, WIDTH)
    stored = features.deserialize_example_np(features.serialize_example(records.encode(_example())))
    # Skipped by the source (`tfds.decode.SkipDecoding`): bytes nobody decodes.
    stored = dict(stored, image1=b"\x89PNG broken", gt_flow=b"zlib bytes")
    decoded = records.decode(stored, where="shard-2[5]", keys=("translation", "depth1"))
    assert list(decoded) == ["depth1", "translation", "id"]
    full = records.decode(
        dict(stored, image1=records.encode(_example())["image1"], gt_flow=_example()["gt_flow"])
    )
    for key in ("depth1", "translation"):
        np.testing.assert_array_equal(decoded[key], full[key])
    with pytest.raises(ValueError, match=r"corrupt image data in shard-2\[5\]/image1"):
        records.decode(stored, where="shard-2[5]", keys=("image1", "depth1"))
    with pytest.raises(ValueError, match=r"unknown record keys \['depth'\]"):
        records.decode(stored, keys=("depth",))
