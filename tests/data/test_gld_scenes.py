"""Tests of the gld_scenes TFDS builder (data/gld_scenes/gld_scenes_dataset_builder.py)."""

import json
import shutil

import numpy as np
import pytest

import data
from data.gld_scenes import dataset_card, example_records, scenes, textures
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
        _, fresh, _, _ = example_records.render_example(config, "test", index)
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
    assert metadata["generator"]["surface_detail"] is True
    assert metadata["texture"]["surface_detail"] is True
    assert metadata["texture"]["detail_contrast"] == scenes.DETAIL_CONTRAST
    assert metadata["texture"]["kinds"] == list(textures.TEXTURES)
    assert dataset_card.texture_card(False) == {
        "kinds": list(textures.TEXTURES),
        "surface_detail": False,
    }
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
    _, example, _, _ = example_records.render_example(configs["tiny_varying"], "train", 0)
    assert not np.allclose(example["intrinsics1"], example["intrinsics2"])


def test_unknown_config_lists_valid_ones():
    with pytest.raises(ValueError, match="gld_scenes/tiny.*gld_scenes/small_varying"):
        data.parse_name("gld_scenes/huge")


def test_bad_worker_count_raises(tmp_path):
    with pytest.raises(ValueError, match="workers"):
        builder_module.Builder(config="tiny", data_dir=str(tmp_path), workers=0)


def _by_hand_flow_signal(example) -> tuple[float, float, float]:
    """A pair's mean and median |true flow| and mean |true flow - rotation-only flow| over
    its valid pixels; the rotation-only flow from the homography K2 R K1^-1."""
    camera_matrix1 = geometry.intrinsics_matrix(example["intrinsics1"].astype(float), HEIGHT, WIDTH)
    camera_matrix2 = geometry.intrinsics_matrix(example["intrinsics2"].astype(float), HEIGHT, WIDTH)
    homography = camera_matrix2 @ example["rotation"].astype(float) @ np.linalg.inv(camera_matrix1)
    v, u = np.mgrid[0:HEIGHT, 0:WIDTH].astype(float)
    pixels = np.stack([u, v, np.ones_like(u)], axis=-1)
    mapped = pixels @ homography.T
    rotation_flow = mapped[..., :2] / mapped[..., 2:] - pixels[..., :2]
    valid = example["gt_flow_valid"]
    flow = example["gt_flow"].astype(float)
    magnitude = np.linalg.norm(flow, axis=-1)[valid]
    parallax = np.linalg.norm(flow - rotation_flow, axis=-1)[valid]
    return magnitude.mean(), np.median(magnitude), parallax.mean()


def test_card_records_the_signal_of_each_split(tiny, tiny_test_split):
    from gld.evaluation import evaluate as evaluation
    from gld.models.baselines import classical

    metadata = json.loads((tiny.data_path / "metadata.json").read_text())
    assert metadata["signal_train"]["pairs"] == metadata["signal_train"]["split_pairs"] == 32
    signal = metadata["signal_test"]
    assert signal["pairs"] == signal["split_pairs"] == 16
    assert "first 16 of 16 pairs" in signal["note"]

    by_hand = np.array([_by_hand_flow_signal(example) for example in tiny_test_split])
    assert signal["gt_flow_px_mean"] == pytest.approx(by_hand[:, 0].mean(), rel=1e-6)
    assert signal["gt_flow_px_median"] == pytest.approx(np.median(by_hand[:, 1]), rel=1e-6)
    assert signal["translational_flow_px_mean"] == pytest.approx(by_hand[:, 2].mean(), rel=1e-6)
    # Hand-held motion: the camera moves, so there is parallax, but rotation moves pixels too.
    assert 0.5 < signal["translational_flow_px_mean"] < signal["gt_flow_px_mean"]

    # The card's triangulation numbers are what the evaluation reports for the baseline.
    source = tiny.as_data_source()["test"]
    for flow, key in (("estimated", "estimated_flow"), ("gt", "gt_flow")):
        per_example, _ = evaluation.evaluate_predictor(
            classical.TriangulationGtPose().predict, source, flow_source=flow
        )
        assert per_example["example_mask"].all()
        expected = per_example["abs_inv"].mean()
        assert signal[f"triangulation_abs_inv_{key}"] == pytest.approx(expected, rel=1e-3, abs=1e-7)
    # Exact flow and pose triangulate almost exactly; the estimated flow does not.
    assert signal["triangulation_abs_inv_gt_flow"] < 1e-4
    assert (
        signal["triangulation_abs_inv_estimated_flow"]
        > 100 * signal["triangulation_abs_inv_gt_flow"]
    )

    # The classical pipeline's numbers are the sfm_flow baseline's on the pairs where it
    # finds a pose (the card counts the others; the evaluation predicts the mean there).
    sfm = classical.SfMFlow(fallback_inv_depth=1.0)
    per_example, _ = evaluation.evaluate_predictor(sfm.predict, source)
    failed = [
        not sfm.estimate_pose(
            example["flow"].astype(np.float64),
            geometry.intrinsics_matrix(example["intrinsics1"].astype(float), HEIGHT, WIDTH),
            geometry.intrinsics_matrix(example["intrinsics2"].astype(float), HEIGHT, WIDTH),
        )[2]
        for example in tiny_test_split
    ]
    failed = np.asarray(failed)
    assert signal["sfm_flow_failed"] == pytest.approx(failed.mean())
    if not failed.all():
        assert signal["sfm_flow_abs_inv"] == pytest.approx(
            per_example["abs_inv"][: len(failed)][~failed].mean(), rel=1e-3
        )

    # The error by texture kind, weighted by each kind's share, is the pixel-weighted
    # error over every valid pixel of the split.
    by_texture = metadata["flow_epe_by_texture_test"]
    assert by_texture["pairs"] == 16
    shares = [by_texture[kind]["pixel_share"] for kind in textures.TEXTURES]
    assert sum(shares) == pytest.approx(1.0)
    weighted = sum(
        by_texture[kind]["epe_px"] * by_texture[kind]["pixel_share"]
        for kind in textures.TEXTURES
        if by_texture[kind]["epe_px"] is not None
    )
    valid_errors = np.concatenate(
        [
            np.linalg.norm(e["flow"] - e["gt_flow"], axis=-1)[e["gt_flow_valid"]]
            for e in tiny_test_split
        ]
    )
    assert weighted == pytest.approx(valid_errors.mean(), rel=1e-3)


def test_card_signal_uses_the_first_card_pairs_of_a_split(tmp_path, monkeypatch):
    monkeypatch.setattr(dataset_card, "CARD_PAIRS", 2)
    config = data.builder_class("gld_scenes").builder_configs["tiny"]
    builder = builder_module.Builder(config=config, data_dir=str(tmp_path))
    list(builder._generate_examples("test", 3))
    signal = builder.info.metadata["signal_test"]
    assert signal["pairs"] == 2 and signal["split_pairs"] == 3
    assert "first 2 of 3 pairs" in signal["note"]
    first_two = [
        dataset_card.signal_statistics(example_records.render_example(config, "test", i)[1])
        for i in range(2)
    ]
    assert signal["gt_flow_px_mean"] == pytest.approx(
        np.mean([pair["gt_flow_px_mean"] for pair in first_two]), rel=1e-5
    )


def test_a_version_1_build_is_never_read_as_version_2(tiny, tiny_test_split, tmp_path):
    # Version 1.0.0's records are the untextured config's: build those, and lay them out
    # as a 1.0.0 build of `tiny` would be.
    untextured = data.prepare("gld_scenes/tiny_untextured", tmp_path / "untextured")
    old = tmp_path / "data" / "gld_scenes" / "tiny" / "1.0.0"
    shutil.copytree(untextured.data_path, old)
    for path in old.iterdir():
        if "tiny_untextured" in path.name:
            path.rename(old / path.name.replace("tiny_untextured", "tiny"))
    info = json.loads((old / "dataset_info.json").read_text())
    info.update(version="1.0.0", configName="tiny")
    (old / "dataset_info.json").write_text(json.dumps(info))
    old_files = sorted((path.name, path.read_bytes()) for path in old.iterdir())

    builder = data.prepare("gld_scenes/tiny", tmp_path / "data")
    assert str(builder.version) == "2.0.0" == data.version("gld_scenes/tiny")
    assert builder.data_path.name == "2.0.0" and builder.data_path != old
    assert "2.0.0" in builder.info.release_notes
    assert sorted((path.name, path.read_bytes()) for path in old.iterdir()) == old_files
    # The new build's images are version 2's (textured); its geometry is the old one's.
    source = builder.as_data_source()["test"]
    old_source = untextured.as_data_source()["test"]
    old_by_index = {}
    for index in range(len(old_source)):
        before = records.decode(old_source[index])
        old_by_index[before["id"].rsplit("/", 1)[1]] = before
    for index in range(3):
        new = records.decode(source[index])
        before = old_by_index[new["id"].rsplit("/", 1)[1]]
        np.testing.assert_array_equal(new["image1"], tiny_test_split[index]["image1"])
        assert not np.array_equal(new["image1"], before["image1"])
        np.testing.assert_array_equal(new["depth1"], before["depth1"])
        np.testing.assert_array_equal(new["gt_flow"], before["gt_flow"])
