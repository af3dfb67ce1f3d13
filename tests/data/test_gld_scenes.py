"""Tests of the gld_scenes TFDS builder (data/gld_scenes/gld_scenes_dataset_builder.py)."""

import json

import numpy as np
import pytest

import data
from data.gld_scenes import gld_scenes_dataset_builder as builder_module
from gld import geometry, records

HEIGHT, WIDTH = 48, 64


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    """The `tiny` config, built once for this module."""
    data_dir = tmp_path_factory.mktemp("gld_scenes_data")
    return data.prepare("gld_scenes/tiny", data_dir)


@pytest.fixture(scope="module")
def tiny_test_split(tiny):
    source = tiny.as_data_source()["test"]
    return [records.decode(source[index], where=f"test[{index}]") for index in range(len(source))]


def test_tiny_build_has_both_splits(tiny):
    assert tiny.info.splits["train"].num_examples == 32
    assert tiny.info.splits["test"].num_examples == 16


def test_records_decode_with_contract_shapes(tiny_test_split):
    shapes = {
        "image1": ((HEIGHT, WIDTH, 3), np.uint8),
        "image2": ((HEIGHT, WIDTH, 3), np.uint8),
        "depth1": ((HEIGHT, WIDTH), np.float32),
        "depth2": ((HEIGHT, WIDTH), np.float32),
        "intrinsics1": ((4,), np.float32),
        "intrinsics2": ((4,), np.float32),
        "rotation": ((3, 3), np.float32),
        "translation": ((3,), np.float32),
        "flow": ((HEIGHT, WIDTH, 2), np.float32),
        "gt_flow": ((HEIGHT, WIDTH, 2), np.float32),
        "gt_flow_valid": ((HEIGHT, WIDTH), np.bool_),
    }
    for example in tiny_test_split:
        for key, (shape, dtype) in shapes.items():
            assert example[key].shape == shape, key
            assert example[key].dtype == dtype, key
        assert np.all(example["depth1"] > 0)
        # The rotation survives storage as a rotation.
        np.testing.assert_allclose(
            example["rotation"] @ example["rotation"].T, np.eye(3), atol=1e-5
        )
    ids = sorted(example["id"] for example in tiny_test_split)
    assert ids == [f"gld_scenes/tiny/test/{index:05d}" for index in range(16)]


def test_stored_records_equal_a_fresh_render(tiny_test_split):
    # Records are a pure function of (config, split, index): a rebuild gives the same data.
    config = data.builder_class("gld_scenes").builder_configs["tiny"]
    for example in tiny_test_split[:3]:
        index = int(example["id"].rsplit("/", 1)[1])
        _, fresh, _, _ = builder_module.render_example(config, "test", index)
        for key in ("image1", "image2", "depth1", "depth2", "gt_flow", "gt_flow_valid"):
            np.testing.assert_array_equal(example[key], fresh[key], err_msg=key)
        np.testing.assert_array_equal(example["flow"], fresh["flow"].astype(np.float16))
        np.testing.assert_array_equal(example["translation"], fresh["translation"])


def test_stored_flow_is_the_estimate_and_gt_flow_is_exact(tiny_test_split):
    for example in tiny_test_split[:4]:
        valid = example["gt_flow_valid"]
        epe = np.linalg.norm(example["flow"] - example["gt_flow"], axis=-1)[valid].mean()
        assert 0 < epe < 5.0  # an estimate: close to, but not equal to, the truth
        camera_matrix1 = geometry.intrinsics_matrix(example["intrinsics1"], HEIGHT, WIDTH)
        camera_matrix2 = geometry.intrinsics_matrix(example["intrinsics2"], HEIGHT, WIDTH)
        flow, _ = geometry.depth_to_flow(
            example["depth1"],
            camera_matrix1,
            camera_matrix2,
            example["rotation"],
            example["translation"],
        )
        np.testing.assert_allclose(flow[valid], example["gt_flow"][valid], atol=1e-3)


def test_metadata_records_settings_and_flow_epe(tiny, tiny_test_split):
    metadata_path = tiny.data_path / "metadata.json"
    metadata = json.loads(metadata_path.read_text())
    assert metadata["flow_estimator"] == "dis"
    assert metadata["generator"]["height"] == HEIGHT
    assert metadata["generator"]["width"] == WIDTH
    errors = [
        np.linalg.norm(e["flow"] - e["gt_flow"], axis=-1)[e["gt_flow_valid"]].mean()
        for e in tiny_test_split
    ]
    # Computed at build time from float32 flow; the stored flow is float16.
    assert metadata["flow_epe_test"] == pytest.approx(np.mean(errors), rel=1e-2)
    assert tiny.info.metadata["flow_epe_test"] == metadata["flow_epe_test"]


def test_worker_pool_gives_the_same_records(tmp_path):
    config = data.builder_class("gld_scenes").builder_configs["tiny"]
    serial = builder_module.Builder(config=config, data_dir=str(tmp_path))
    parallel = builder_module.Builder(config=config, data_dir=str(tmp_path), workers=2)
    serial_records = list(serial._generate_examples("test", 3))
    parallel_records = list(parallel._generate_examples("test", 3))
    assert [key for key, _ in serial_records] == [key for key, _ in parallel_records]
    for (_, first), (_, second) in zip(serial_records, parallel_records, strict=True):
        assert first["image1"] == second["image1"]  # PNG bytes
        np.testing.assert_array_equal(first["gt_flow"], second["gt_flow"])


def test_varying_configs_perturb_intrinsics():
    configs = data.builder_class("gld_scenes").builder_configs
    assert configs["small"].height == 96 and configs["small"].width == 128
    assert configs["full"].num_train == 40_000
    for name in ("tiny", "small", "full"):
        assert configs[name].intrinsics_jitter == 0.0
        assert configs[f"{name}_varying"].intrinsics_jitter == pytest.approx(0.2)
    _, example, _, _ = builder_module.render_example(configs["tiny_varying"], "train", 0)
    assert not np.allclose(example["intrinsics1"], example["intrinsics2"])


def test_unknown_config_lists_valid_ones():
    with pytest.raises(ValueError, match="gld_scenes/tiny.*gld_scenes/small_varying"):
        data.parse_name("gld_scenes/huge")


def test_bad_worker_count_raises(tmp_path):
    with pytest.raises(ValueError, match="workers"):
        builder_module.Builder(config="tiny", data_dir=str(tmp_path), workers=0)
