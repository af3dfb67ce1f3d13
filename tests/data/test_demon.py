"""Tests of data/demon: reader, pair generation, damage handling, checksums and the builder.

The DeMoN files are written by `demon_files` (h5py, lz4, OpenCV) independently of
the reader, then every field read back is compared with what was written.
"""

from __future__ import annotations

import demon_files
import h5py
import numpy as np
import pytest

import data
from data.demon import checksums, damage, images, pairs, reader
from gld import records

HEIGHT, WIDTH = pairs.HEIGHT, pairs.WIDTH


def float16_close(actual, expected):
    """Depth round trips through float16: ~1e-3 relative precision."""
    np.testing.assert_allclose(actual, expected, rtol=1e-3, atol=0)


@pytest.fixture
def rng():
    return np.random.default_rng(7)


def write_file(path, scenes):
    """scenes: list of (name, views, viewpoint_pairs[, view_options])."""
    with h5py.File(path, "w") as h5_file:
        h5_file.create_group(".config")
        for scene in scenes:
            demon_files.write_scene(h5_file, *scene)
    return path


# --- reader -------------------------------------------------------------------------------


def test_view_fields_read_back(tmp_path, rng):
    views = demon_files.moving_views(rng, 2, HEIGHT, WIDTH)
    path = write_file(tmp_path / "scenes.h5", [("s", views, (0, 1))])
    with reader.DemonFile(path) as demon_file:
        for index, written in enumerate(views):
            view = demon_file.view("s", index)
            np.testing.assert_array_equal(view.image, written["image"])
            float16_close(view.depth, written["depth"])
            k = written["camera_matrix"]
            np.testing.assert_allclose(
                view.intrinsics,
                [k[0, 0] / WIDTH, k[1, 1] / HEIGHT, k[0, 2] / WIDTH, k[1, 2] / HEIGHT],
            )
            np.testing.assert_allclose(view.rotation, written["rotation"], atol=1e-12)
            np.testing.assert_allclose(view.translation, written["translation"])


def test_camera_rotation_is_column_major():
    rotation = demon_files.rotation_about([1.0, 2.0, 0.5], 30.0)
    assert not np.allclose(rotation, rotation.T)
    values = demon_files.camera_values(np.diag([100.0, 120.0, 1.0]), rotation, [1.0, 2.0, 3.0])
    camera_matrix, parsed_rotation, translation = reader.parse_camera(values)
    np.testing.assert_allclose(parsed_rotation, rotation)
    np.testing.assert_allclose(translation, [1.0, 2.0, 3.0])
    assert camera_matrix[0, 0] == 100.0 and camera_matrix[1, 1] == 120.0


def test_ray_length_depth_becomes_camera_z(tmp_path, rng):
    views = demon_files.moving_views(rng, 2, HEIGHT, WIDTH)
    path = write_file(
        tmp_path / "ray.h5", [("s", views, (0, 1), {0: {"depth_metric": "ray_length"}})]
    )
    with reader.DemonFile(path) as demon_file:
        ray_view = demon_file.view("s", 0)
    # Off-centre pixels have rays much longer than z: the conversion must divide them out.
    assert demon_files.ray_norms(views[0]["camera_matrix"], HEIGHT, WIDTH).max() > 1.2
    float16_close(ray_view.depth, views[0]["depth"])


def test_demons_webp_decoding_is_at_hand():
    # A dependency of gld (setup.cfg): DeMoN's protocol, the default, decodes with it.
    assert images.webp_decoder_available()


def test_webp_decoders_agree_on_lossless_images(rng):
    image = demon_files.texture(rng, HEIGHT, WIDTH)
    data = demon_files.webp_bytes(image)
    for decoder in images.IMAGE_DECODERS:
        np.testing.assert_array_equal(images.decode_image(data, decoder=decoder), image)


def test_demon_webp_decoder_bypasses_filtering_and_fancy_upsampling(tmp_path, rng):
    views = demon_files.moving_views(rng, 2, HEIGHT, WIDTH)
    lossy = demon_files.webp_bytes(views[0]["image"], quality=50)
    opencv = images.decode_image(lossy, decoder="opencv").astype(int)
    # libwebp with both options off is OpenCV's decoding, bit for bit ...
    plain = images.decode_webp_libwebp(lossy, bypass_filtering=False, no_fancy_upsampling=False)
    np.testing.assert_array_equal(plain, opencv)
    # ... and each option on its own changes the image (both fields are really set).
    for bypass_filtering, no_fancy_upsampling in ((True, False), (False, True)):
        alone = images.decode_webp_libwebp(
            lossy, bypass_filtering=bypass_filtering, no_fancy_upsampling=no_fancy_upsampling
        )
        assert np.abs(alone - opencv).mean() > 0.1
    path = write_file(tmp_path / "lossy.h5", [("s", views, (0, 1), {0: {"image_data": lossy}})])
    with reader.DemonFile(path, image_decoder="demon") as demon_file:
        image = demon_file.view("s", 0).image
    np.testing.assert_array_equal(image, images.decode_webp_libwebp(lossy))
    assert np.abs(image - opencv).mean() > 1.0


def test_image_decoder_choice(monkeypatch):
    with pytest.raises(ValueError, match="unknown image decoder"):
        images.resolve_image_decoder("pillow")
    assert images.resolve_image_decoder("opencv") == "opencv"
    # DeMoN's decoding is the default, whatever is installed: the same options, the
    # same records (without `webp`, lossy images are refused, not approximated).
    for available in (False, True):
        monkeypatch.setattr(images, "webp_decoder_available", lambda available=available: available)
        assert images.resolve_image_decoder(None) == "demon"
        assert images.resolve_image_decoder("demon") == "demon"


def test_demon_decoding_of_lossless_images_needs_no_webp_package(rng, monkeypatch):
    image = demon_files.texture(rng, 24, 32)
    lossless, lossy = demon_files.webp_bytes(image), demon_files.webp_bytes(image, quality=80)
    assert images.webp_compression(lossless) == "lossless"
    assert images.webp_compression(lossy) == "lossy"
    assert images.webp_compression(b"RIFF\x04\x00\x00\x00WEBP") is None
    monkeypatch.setattr(images, "webp_decoder_available", lambda: False)
    # Lossless WebP has the same pixels whatever libwebp's options: DeMoN's, exactly.
    np.testing.assert_array_equal(images.decode_image(lossless, decoder="demon"), image)
    with pytest.raises(images.MissingDecoderError, match="pip install webp") as error:
        images.decode_image(lossy, "a.h5/s/frames/t0/v0/image", decoder="demon")
    assert "a.h5/s/frames/t0/v0/image" in str(error.value)
    assert "--image_decoder=opencv" in str(error.value)
    # A dependency of gld, not an extra.
    assert "pip install -e . installs" in str(error.value) and "[demon]" not in str(error.value)
    assert images.decode_image(lossy, decoder="opencv").shape == (24, 32, 3)
    # Damaged bytes stay damage, whatever is installed.
    for damaged in (b"not a webp", lossy[:60]):
        with pytest.raises(damage.DamagedDataError, match="corrupt_image"):
            images.decode_image(damaged, decoder="demon")


def _lossy_scene(rng, name="s", quality=50):
    """(name, views, pairs, options) of a two-view scene whose images are lossy WebP."""
    views = demon_files.moving_views(rng, 2, HEIGHT, WIDTH)
    options = {
        index: {"image_data": demon_files.webp_bytes(view["image"], quality=quality)}
        for index, view in enumerate(views)
    }
    return (name, views, (0, 1), options)


def test_a_default_build_of_lossy_images_without_webp_is_refused_in_one_line(
    tmp_path, rng, monkeypatch
):
    manual_dir = tmp_path / "manual"
    manual_dir.mkdir()
    write_file(manual_dir / "scenes11_test.h5", [_lossy_scene(rng)])
    monkeypatch.setattr(images, "webp_decoder_available", lambda: False)
    datasets = tmp_path / "datasets"
    with pytest.raises(ImportError) as error:
        data.prepare("demon/scenes11", datasets, manual_dir, verify_checksums=False)
    assert isinstance(error.value, images.MissingDecoderError)
    message = str(error.value)
    assert "\n" not in message
    assert "needs the `webp` package for the lossy images of scenes11_test.h5" in message
    assert "pip install webp" in message and "--image_decoder=opencv" in message
    assert not data.get_builder("demon/scenes11", datasets).is_prepared()
    # The approximation, asked for by name, builds.
    builder = data.prepare(
        "demon/scenes11", datasets, manual_dir, verify_checksums=False, image_decoder="opencv"
    )
    assert builder.info.metadata["build_options"]["test"]["image_decoder"] == "opencv"


def test_a_default_build_decodes_webp_as_demons_reader(tmp_path, rng):
    manual_dir = tmp_path / "manual"
    manual_dir.mkdir()
    scene = _lossy_scene(rng)
    write_file(manual_dir / "scenes11_test.h5", [scene])
    builder = data.prepare(
        "demon/scenes11", tmp_path / "datasets", manual_dir, verify_checksums=False
    )
    (record,) = [records.decode(r) for r in builder.as_data_source(split="test")]
    lossy = scene[3][0]["image_data"]
    np.testing.assert_array_equal(record["image1"], images.decode_webp_libwebp(lossy))
    opencv = images.decode_image(lossy, decoder="opencv")
    assert np.abs(record["image1"].astype(int) - opencv).mean() > 1.0
    assert builder.info.metadata["build_options"]["test"]["image_decoder"] == "demon"


def test_viewpoint_pairs_train_all_test_first(tmp_path, rng):
    views = demon_files.moving_views(rng, 3, 12, 16)
    path = write_file(
        tmp_path / "pairs.h5",
        [("listed", views, (0, 1, 0, 2, 2, 1)), ("unlisted", views, None)],
    )
    with reader.DemonFile(path) as demon_file:
        assert demon_file.pairs("listed", "train") == [(0, 1), (0, 2), (2, 1)]
        assert demon_file.pairs("listed", "test") == [(0, 1)]
        assert demon_file.pairs("unlisted", "train") == [
            (0, 1),
            (0, 2),
            (1, 0),
            (1, 2),
            (2, 0),
            (2, 1),
        ]
        assert demon_file.pairs("unlisted", "test") == [(0, 1)]


def test_reserved_groups_skipped_and_sorted(tmp_path, rng):
    views = demon_files.moving_views(rng, 2, 12, 16)
    path = write_file(tmp_path / "groups.h5", [("zeta", views), ("alpha", views)])
    with h5py.File(path, "a") as h5_file:
        demon_files.write_scene(h5_file, ".hidden", views)
    with reader.DemonFile(path) as demon_file:
        assert demon_file.groups() == ["alpha", "zeta"]


def test_missing_file_names_path(tmp_path):
    with pytest.raises(FileNotFoundError, match="nothing.h5"):
        reader.DemonFile(tmp_path / "nothing.h5")


# --- resizing and records -------------------------------------------------------------------


def test_records_fields_and_relative_pose(tmp_path, rng):
    views = demon_files.moving_views(rng, 3, HEIGHT, WIDTH)
    path = write_file(tmp_path / "pose.h5", [("s", views, (0, 2, 1, 0))])
    examples = dict(pairs.generate([path], "train"))
    assert sorted(examples) == ["pose.h5/s/0-2", "pose.h5/s/1-0"]
    example = examples["pose.h5/s/0-2"]
    first, second = views[0], views[2]
    np.testing.assert_array_equal(example["image1"], first["image"])
    np.testing.assert_array_equal(example["image2"], second["image"])
    float16_close(example["depth1"], first["depth"])
    float16_close(example["depth2"], second["depth"])
    # A world point seen from both cameras: X2 = R X1 + t must hold for the stored pose.
    world_points = rng.normal(size=(5, 3))
    in_first = world_points @ first["rotation"].T + first["translation"]
    in_second = world_points @ second["rotation"].T + second["translation"]
    predicted = in_first @ example["rotation"].T.astype(np.float64) + example["translation"]
    np.testing.assert_allclose(predicted, in_second, atol=1e-5)
    # Raw scale: the pipeline normalises ||t|| = 1 later, so the record keeps the baseline.
    camera_centres = [-v["rotation"].T @ v["translation"] for v in (first, second)]
    np.testing.assert_allclose(
        np.linalg.norm(example["translation"]),
        np.linalg.norm(camera_centres[1] - camera_centres[0]),
        rtol=1e-5,
    )
    assert example["flow"].shape == (HEIGHT, WIDTH, 2)
    assert example["gt_flow"].shape == (HEIGHT, WIDTH, 2)
    assert example["gt_flow_valid"].mean() > 0.3
    records.encode(example)  # accepted by the shared record format


def test_resize_to_256x192_rescales_intrinsics_and_depth(tmp_path, rng):
    height, width = 2 * HEIGHT, 2 * WIDTH
    views = demon_files.moving_views(rng, 2, height, width)
    views[0]["depth"][:40, :60] = np.nan  # invalid corner, must stay invalid
    path = write_file(tmp_path / "big.h5", [("s", views, (0, 1))])
    ((_, example),) = pairs.generate([path], "test")
    k = views[0]["camera_matrix"]
    np.testing.assert_allclose(
        example["intrinsics1"],
        [k[0, 0] / width, k[1, 1] / height, k[0, 2] / width, k[1, 2] / height],
        rtol=1e-6,
    )
    # INTER_AREA at 2x is the mean of each 2x2 block.
    block_mean = views[0]["image"].reshape(HEIGHT, 2, WIDTH, 2, 3).astype(float).mean(axis=(1, 3))
    assert np.abs(example["image1"] - block_mean).max() <= 1.0
    # DeMoN's nearest sampling (the default): at 2x, each 2x2 block's upper-left pixel.
    expected = np.nan_to_num(views[0]["depth"].astype(np.float16).astype(np.float32))[::2, ::2]
    np.testing.assert_array_equal(example["depth1"], expected)
    assert np.all(example["depth1"][:20, :30] == 0)


def _demon_rows_cols():
    """DeMoN's reader at 640x480 -> 256x192 takes pixel (floor(2.5 y), floor(2.5 x))."""
    rows = (np.arange(HEIGHT) * 5) // 2
    cols = (np.arange(WIDTH) * 5) // 2
    assert list(rows[:5]) == [0, 2, 5, 7, 10] and cols[-1] == 637
    return rows, cols


def test_demon_resampling_of_a_640x480_map_by_hand():
    row, col = np.mgrid[0:480, 0:640].astype(np.float32)
    depth = 1.0 + row + col / 1000.0  # every pixel distinct and exact in float32
    depth[2, 2] = np.nan  # sampled by output pixel (1, 1): invalid there
    depth[3, 3] = 0.0  # sampled by the centred convention only
    resized = pairs.resize_depth_demon(depth, HEIGHT, WIDTH)
    rows, cols = _demon_rows_cols()
    expected = np.nan_to_num(depth)[rows[:, None], cols[None, :]]
    np.testing.assert_array_equal(resized, expected)
    assert resized[0, 0] == 1.0 and resized[0, 1] == 1.002 and resized[1, 0] == 3.0
    assert resized[1, 1] == 0.0  # no hole filling
    # gld's centred convention samples (floor(2.5 y + 1.25), ...): another pixel everywhere,
    # and at (1, 1) it fills the hole left by (3, 3) from a covered neighbour.
    centred = pairs.resize_depth_centred(depth, HEIGHT, WIDTH)
    assert centred[0, 0] == depth[1, 1] and centred[0, 1] == depth[1, 3]
    assert centred[1, 1] in (depth[3, 4], depth[4, 3])
    assert np.count_nonzero(centred != resized) == HEIGHT * WIDTH


@pytest.mark.parametrize("depth_metric", ["camera_z", "ray_length"])
def test_demon_resampling_of_a_640x480_file(tmp_path, rng, depth_metric):
    views = demon_files.moving_views(rng, 2, 480, 640)
    path = write_file(
        tmp_path / "vga.h5", [("s", views, (0, 1), {0: {"depth_metric": depth_metric}})]
    )
    ((_, example),) = pairs.generate([path], "test")
    rows, cols = _demon_rows_cols()
    camera_matrix = views[0]["camera_matrix"]
    stored = views[0]["depth"]
    if depth_metric == "ray_length":
        stored = stored * demon_files.ray_norms(camera_matrix, 480, 640)
    stored = stored.astype(np.float16).astype(np.float64)[rows[:, None], cols[None, :]]
    if depth_metric == "ray_length":
        # DeMoN converts after resampling, with the rays of the 256x192 pixel centres.
        scaled = np.diag([WIDTH / 640, HEIGHT / 480, 1.0]) @ camera_matrix
        stored = stored / demon_files.ray_norms(scaled, HEIGHT, WIDTH)
    np.testing.assert_allclose(example["depth1"], stored, rtol=2e-6)


def test_centred_resampling_keeps_a_single_sparse_reading():
    depth = np.zeros((480, 640), np.float32)
    depth[101, 333] = 4.5  # the one pixel a range sensor sees
    resized = pairs.resize_depth_centred(depth, HEIGHT, WIDTH)
    assert np.count_nonzero(resized) == 1
    row, col = np.argwhere(resized)[0]
    assert (row, col) == (int(101.5 * 0.4), int(333.5 * 0.4))
    assert resized[row, col] == 4.5
    # DeMoN's convention samples rows 0, 2, 5, 7, ...: row 101 is not among them.
    assert np.count_nonzero(pairs.resize_depth_demon(depth, HEIGHT, WIDTH)) == 0


@pytest.mark.parametrize("resampling", sorted(pairs.DEPTH_RESAMPLING))
def test_resize_never_mixes_depths(resampling):
    depth = np.where(np.arange(640)[None, :] < 321, 1.0, 9.0) * np.ones((480, 1))
    depth[::7, ::5] = np.nan
    resized = pairs.DEPTH_RESAMPLING[resampling](depth.astype(np.float32), HEIGHT, WIDTH)
    assert set(np.unique(resized)) <= {0.0, 1.0, 9.0}


# --- baselines ------------------------------------------------------------------------------


def _tiny_baseline_views(rng, baseline):
    """Two views 2.0-3.6 m from a wall (median depth ~2.8 m), `baseline` apart along x."""
    first, second = demon_files.moving_views(rng, 2, HEIGHT, WIDTH)
    camera_centre = -first["rotation"].T @ first["translation"]
    moved = camera_centre + first["rotation"].T @ [baseline, 0.0, 0.0]
    second = dict(second, rotation=first["rotation"], translation=-first["rotation"] @ moved)
    return [first, second]


def test_tiny_baseline_test_pair_is_kept_and_counted(tmp_path, rng):
    views = demon_files.moving_views(rng, 2, HEIGHT, WIDTH)
    tiny = _tiny_baseline_views(rng, 2e-4)  # 2e-4 / 2.8 = 7e-5 x median depth
    scenes = [(name, views) for name in "abcd"] + [("e_tiny", tiny)]
    path = write_file(tmp_path / "test.h5", scenes)
    report = pairs.BuildReport("test")
    examples = dict(pairs.generate([path], "test", max_bad_fraction=0.0, report=report))
    assert len(examples) == 5
    np.testing.assert_allclose(
        np.linalg.norm(examples["test.h5/e_tiny/0-1"]["translation"]), 2e-4, rtol=1e-3
    )
    assert report.as_dict()["small_baseline_written"] == 1
    assert report.as_dict()["files"]["test.h5"]["small_baseline_written"] == 1
    assert "1 written pairs have a small baseline" in report.format()
    # The input pipeline can normalise it (it refuses only DeMoN's ||t|| < 1e-6).
    from gld import contract

    example = examples["test.h5/e_tiny/0-1"]
    normalised = contract.normalise_scale(
        {"id": "e", "translation": example["translation"], "depth": example["depth1"]}
    )
    np.testing.assert_allclose(np.linalg.norm(normalised["translation"]), 1.0, rtol=1e-6)


def test_relative_baseline_threshold_is_a_filter_not_damage(tmp_path, rng):
    views = demon_files.moving_views(rng, 2, HEIGHT, WIDTH)
    tiny = _tiny_baseline_views(rng, 2e-4)
    path = write_file(tmp_path / "train.h5", [("a", views), ("b_tiny", tiny)])
    # Training drops it by default; a filtered pair neither counts as damage nor stops
    # a strict build.
    report = pairs.BuildReport("train")
    generated = pairs.generate([path], "train", strict=True, max_bad_fraction=0, report=report)
    ids = [example_id for example_id, _ in generated]
    assert ids == ["train.h5/a/0-1"]
    assert report.skipped == {"train.h5": {"small_baseline": 1}} and report.num_damaged == 0
    # The threshold is an option: on for the test split when asked, off for training.
    test_ids = [i for i, _ in pairs.generate([path], "test", min_relative_baseline=1e-4)]
    assert test_ids == ["train.h5/a/0-1"]
    train_ids = [i for i, _ in pairs.generate([path], "train", min_relative_baseline=0.0)]
    assert train_ids == ["train.h5/b_tiny/0-1", "train.h5/a/0-1"]  # DeMoN's order


def test_pairs_without_a_baseline_are_skipped_as_demon_does_and_are_not_damage(tmp_path, rng):
    views = demon_files.moving_views(rng, 2, HEIGHT, WIDTH)
    still = _damage("zero_translation", demon_files.moving_views(rng, 2, HEIGHT, WIDTH), rng)
    scenes = [("a", views), ("b", _tiny_baseline_views(rng, 5e-7)), ("c", views), ("d", *still)]
    path = write_file(tmp_path / "t.h5", scenes)
    report = pairs.BuildReport("test")
    # Half the pairs have no baseline: neither max_bad_fraction (0.05) nor strict stops.
    ids = [i for i, _ in pairs.generate([path], "test", strict=True, report=report)]
    assert ids == ["t.h5/c/0-1", "t.h5/a/0-1"]
    assert report.skipped == {"t.h5": {"zero_translation": 2}}
    summary = report.as_dict()
    assert summary["pairs_damaged"] == 0
    assert summary["pairs_filtered"] == {"zero_translation": 2, "small_baseline": 0}
    assert "2 skipped (0 damaged; not damage: 2 without a baseline, ||t|| < 1e-06" in (
        report.format()
    )


# --- damage ---------------------------------------------------------------------------------


def _damage(kind, views, rng):
    """(scene views, viewpoint_pairs, view_options) of a scene with one kind of damage."""
    options = {}
    if kind == "corrupt_image":
        options = {1: {"image_data": demon_files.webp_bytes(views[1]["image"])[:60]}}
    elif kind == "truncated_lz4":
        options = {0: {"depth_data": demon_files.lz4_depth_bytes(views[0]["depth"])[:-40]}}
    elif kind == "wrong_extents":
        options = {0: {"extents": [HEIGHT + 1, WIDTH]}}
    elif kind in ("nan_depth", "inf_depth", "negative_depth"):
        value = {"nan_depth": np.nan, "inf_depth": np.inf, "negative_depth": -2.0}[kind]
        views = [dict(views[0], depth=np.full_like(views[0]["depth"], value)), views[1]]
    elif kind == "missing_camera":
        options = {1: {"camera": False}}
    elif kind == "bad_camera":
        views = [dict(views[0], rotation=2.0 * views[0]["rotation"]), views[1]]
    elif kind == "zero_translation":
        views = [
            views[0],
            dict(views[1], rotation=views[0]["rotation"], translation=views[0]["translation"]),
        ]
    elif kind == "one_view":
        views = views[:1]
    elif kind == "bad_pairs":
        return views, (0, 5), options
    return views, (0, 1), options


DAMAGE_REASONS = {
    "corrupt_image": "corrupt_image",
    "truncated_lz4": "corrupt_depth",
    "wrong_extents": "wrong_extents",
    "nan_depth": "invalid_depth",
    "inf_depth": "invalid_depth",
    "negative_depth": "invalid_depth",
    "missing_camera": "missing_camera",
    "bad_camera": "bad_camera",
    "one_view": "too_few_views",
    "bad_pairs": "bad_viewpoint_pairs",
}


@pytest.mark.parametrize("kind", sorted(DAMAGE_REASONS))
def test_damaged_pair_skipped_and_counted(tmp_path, rng, kind):
    good = demon_files.moving_views(rng, 2, HEIGHT, WIDTH)
    damaged = _damage(kind, demon_files.moving_views(rng, 2, HEIGHT, WIDTH), rng)
    path = write_file(tmp_path / "damaged.h5", [("a_good", good), ("b_bad", *damaged)])
    report = pairs.BuildReport("test")
    ids = [
        example_id
        for example_id, _ in pairs.generate([path], "test", max_bad_fraction=0.5, report=report)
    ]
    assert ids == ["damaged.h5/a_good/0-1"]
    assert report.as_dict()["files"]["damaged.h5"] == {
        "written": 1,
        "skipped": {DAMAGE_REASONS[kind]: 1},
        "small_baseline_written": 0,
        "no_valid_depth_written": 0,
    }
    assert report.num_damaged == 1
    assert "b_bad" in report.first_errors[0]


def test_strict_fails_at_first_damaged_pair(tmp_path, rng):
    views = demon_files.moving_views(rng, 2, HEIGHT, WIDTH)
    scenes = [("a", *_damage("corrupt_image", views, rng)), ("b", views)]
    scenes.append(("c", *_damage("truncated_lz4", views, rng)))
    path = write_file(tmp_path / "strict.h5", scenes)
    written = []
    # DeMoN's order: c, b, a.
    with pytest.raises(damage.DamagedDataError, match="strict.h5/c/0-1") as error:
        for example_id, _ in pairs.generate([path], "test", strict=True):
            written.append(example_id)
    assert error.value.reason == "corrupt_depth"
    assert written == []


def test_bad_share_above_threshold_fails_the_build(tmp_path, rng):
    views = demon_files.moving_views(rng, 2, HEIGHT, WIDTH)
    scenes = [(name, views) for name in ("a", "b", "c")]
    scenes.append(("d", *_damage("missing_camera", views, rng)))
    path = write_file(tmp_path / "share.h5", scenes)
    assert len(list(pairs.generate([path], "test", max_bad_fraction=0.25))) == 3
    with pytest.raises(ValueError, match="1 of 4 planned pairs are damaged"):
        list(pairs.generate([path], "test", max_bad_fraction=0.2))


def test_damaged_view_skips_only_its_pairs(tmp_path, rng):
    views = demon_files.moving_views(rng, 3, HEIGHT, WIDTH)
    options = {2: {"image_data": b"not a webp"}}
    path = write_file(tmp_path / "train.h5", [("s", views, (0, 1, 0, 2, 2, 1, 1, 0), options)])
    report = pairs.BuildReport("train")
    ids = [i for i, _ in pairs.generate([path], "train", max_bad_fraction=0.5, report=report)]
    assert ids == ["train.h5/s/0-1", "train.h5/s/1-0"]
    assert report.skipped == {"train.h5": {"corrupt_image": 2}}


# --- checksums and leaky files --------------------------------------------------------------


@pytest.mark.parametrize(
    "name, leaky",
    [
        ("rgbd_10_to_20_3d_train.h5", True),
        ("rgbd_20_to_inf_handheld_train.h5", True),
        ("rgbd_bugfix_10_to_20_3d_train.h5", False),
        ("rgbd_10_to_20_simple_train.h5", False),
        ("rgbd_test.h5", False),
    ],
)
def test_leaky_rgbd_names(name, leaky):
    assert checksums.is_leaky_rgbd_file(name) == leaky


def test_checksum_mismatch_and_unknown_files(tmp_path):
    known = tmp_path / "sun3d_test.h5"
    known.write_bytes(b"not the published file")
    with pytest.raises(ValueError, match="MD5"):
        checksums.verify(known)
    unknown = tmp_path / "custom_train.h5"
    unknown.write_bytes(b"anything")
    checksums.verify(unknown)  # no published sum: not checked
    assert checksums.md5(unknown) == "f0e166dc34d14d6c228ffac576c9a43c"


# --- builder --------------------------------------------------------------------------------


def test_builder_refuses_leaky_rgbd_files(tmp_path, rng):
    manual_dir = tmp_path / "manual"
    manual_dir.mkdir()
    views = demon_files.moving_views(rng, 2, 12, 16)
    write_file(manual_dir / "rgbd_test.h5", [("s", views)])
    write_file(manual_dir / "rgbd_10_to_20_3d_train.h5", [("s", views)])
    with pytest.raises(ValueError, match="leak|contain samples of rgbd_test"):
        data.prepare("demon/rgbd", tmp_path / "datasets", manual_dir, verify_checksums=False)


def test_builder_requires_every_file_of_a_split(tmp_path, rng):
    manual_dir = tmp_path / "manual"
    manual_dir.mkdir()
    write_file(
        manual_dir / "sun3d_train_0.1m_to_0.2m.h5",
        [("s", demon_files.moving_views(rng, 2, 12, 16))],
    )
    with pytest.raises(FileNotFoundError, match="sun3d_train_0.01m_to_0.1m.h5"):
        data.prepare("demon/sun3d", tmp_path / "datasets", manual_dir, verify_checksums=False)


def test_file_check_reads_structure_only(tmp_path, rng, monkeypatch):
    path = write_file(tmp_path / "scenes.h5", [("s", demon_files.moving_views(rng, 2, 12, 16))])

    def no_decoding(*args, **kwargs):
        raise AssertionError("the file check must not decode images or depth")

    monkeypatch.setattr(images, "decode_image", no_decoding)
    monkeypatch.setattr(reader, "decode_depth", no_decoding)
    reader.check_files([path])
    no_views = write_file(tmp_path / "no_views.h5", [])
    with h5py.File(no_views, "a") as h5_file:
        h5_file.create_group("s/frames/t0")
    assert "none of its 1 scene groups has frames/t0/v0" in reader.file_problem(no_views)


def test_builder_checks_every_file_before_building_any_split(tmp_path, rng, monkeypatch):
    """A truncated test file fails the build at once, not after the train split."""
    manual_dir = tmp_path / "manual"
    manual_dir.mkdir()
    views = demon_files.moving_views(rng, 2, 12, 16)
    write_file(manual_dir / "scenes11_train.h5", [("a", views), ("b", views[::-1])])
    test_file = write_file(manual_dir / "scenes11_test.h5", [("a", views)])
    test_file.write_bytes(test_file.read_bytes()[: test_file.stat().st_size // 2])
    generated = []
    generate = pairs.generate

    def recording_generate(paths, split, **kwargs):
        generated.append(split)
        return generate(paths, split, **kwargs)

    monkeypatch.setattr(pairs, "generate", recording_generate)
    with pytest.raises(ValueError) as error:
        data.prepare("demon/scenes11", tmp_path / "datasets", manual_dir, verify_checksums=False)
    assert generated == []  # no split was built
    assert f"1 of 2 DeMoN file(s) unusable:\n  {test_file} is not a readable HDF5 file" in str(
        error.value
    )
    assert "truncated file" in str(error.value)
    assert not list((tmp_path / "datasets").rglob("*.array_record*"))

    write_file(manual_dir / "scenes11_train.h5", [])  # an HDF5 file without scenes
    with pytest.raises(ValueError, match="2 of 2 DeMoN file") as error:
        data.prepare("demon/scenes11", tmp_path / "datasets", manual_dir, verify_checksums=False)
    assert f"{manual_dir / 'scenes11_train.h5'} holds no scene groups" in str(error.value)


def test_builder_builds_test_split_with_report(tmp_path, rng, capsys):
    manual_dir = tmp_path / "manual"
    manual_dir.mkdir()
    views = demon_files.moving_views(rng, 2, HEIGHT, WIDTH)
    scenes = [("a", views), ("b", *_damage("truncated_lz4", views, rng)), ("c", views[::-1])]
    scenes.append(("d_tiny", _tiny_baseline_views(rng, 2e-4)))
    write_file(manual_dir / "scenes11_test.h5", scenes)
    builder = data.prepare(
        "demon/scenes11",
        tmp_path / "datasets",
        manual_dir,
        verify_checksums=False,
        max_bad_fraction=0.5,
    )
    assert list(builder.info.splits) == ["test"]  # no training files: split left out
    source = builder.as_data_source(split="test")
    examples = {}
    for index in range(len(source)):
        example = records.decode(source[index])
        examples[example["id"]] = example
    assert sorted(examples) == [f"scenes11_test.h5/{name}/0-1" for name in ("a", "c", "d_tiny")]
    np.testing.assert_array_equal(examples["scenes11_test.h5/c/0-1"]["image1"], views[1]["image"])
    float16_close(examples["scenes11_test.h5/a/0-1"]["depth1"], views[0]["depth"])
    report = builder.info.metadata["build_report"]["test"]
    assert report["files"]["scenes11_test.h5"] == {
        "written": 3,
        "skipped": {"corrupt_depth": 1},
        "small_baseline_written": 1,
        "no_valid_depth_written": 0,
    }
    assert (
        "scenes11_test.h5: 3 pairs written (1 with a small baseline), 1 skipped (corrupt_depth: 1)"
        in capsys.readouterr().out
    )
    options = builder.info.metadata["build_options"]["test"]
    assert options["min_relative_baseline"] == 0.0 and options["depth_resampling"] == "demon"
    assert options["image_decoder"] == "demon" and options["order"] == "demon"


def test_builder_defaults(tmp_path):
    scenes11 = data.get_builder("demon/scenes11", tmp_path)
    # The builder writes what grain and TFDS read without TensorFlow.
    assert scenes11.info.file_format.value == "array_record"
    assert scenes11.build_options("train")["min_relative_baseline"] == 1e-4
    assert scenes11.build_options("test")["min_relative_baseline"] == 0.0
    assert scenes11.build_options("test")["depth_resampling"] == "demon"
    custom = data.get_builder("demon/custom", tmp_path, min_relative_baseline=1e-3)
    assert custom.build_options("test")["min_relative_baseline"] == 1e-3
    # DeMoN's protocol is every config's default, custom's included.
    for config in ("scenes11", "sun3d", "rgbd", "custom"):
        options = data.get_builder(f"demon/{config}", tmp_path).build_options("test")
        assert options["depth_resampling"] == "demon", config
        assert options["image_decoder"] == "demon", config
        assert options["order"] == "demon", config
    with pytest.raises(ValueError, match="depth_resampling"):
        data.get_builder("demon/sun3d", tmp_path, depth_resampling="bilinear")


def test_records_are_stored_and_read_in_demons_order(tmp_path, rng):
    """DeMoN's reader op sorts a file's scene groups and takes them from the back; the
    records keep that order (not TFDS's key hash), so index i is DeMoN's pair i."""
    manual_dir = tmp_path / "manual"
    manual_dir.mkdir()
    views = demon_files.moving_views(rng, 2, 24, 32)
    write_file(manual_dir / "scenes11_test.h5", [(f"g{index}", views) for index in range(5)])
    builder = data.prepare(
        "demon/scenes11", tmp_path / "datasets", manual_dir, verify_checksums=False
    )
    source = builder.as_data_source(split="test")
    ids = [records.decode(source[index])["id"] for index in range(len(source))]
    assert ids == [f"scenes11_test.h5/g{index}/0-1" for index in (4, 3, 2, 1, 0)]
    assert builder.info.metadata["build_options"]["test"]["order"] == "demon"


def test_custom_resamples_depth_as_demon_by_default(tmp_path, rng):
    manual_dir = tmp_path / "manual"
    manual_dir.mkdir()
    views = demon_files.moving_views(rng, 2, 240, 320)  # 1.25x 256x192: the rules differ
    write_file(manual_dir / "custom_test.h5", [("s", views)])
    builder = data.prepare("demon/custom", tmp_path / "datasets", manual_dir)
    (record,) = [records.decode(r) for r in builder.as_data_source(split="test")]
    stored = views[0]["depth"].astype(np.float16).astype(np.float32)
    np.testing.assert_array_equal(record["depth1"], pairs.resize_depth_demon(stored, HEIGHT, WIDTH))
    assert np.any(record["depth1"] != pairs.resize_depth_centred(stored, HEIGHT, WIDTH))
    assert builder.info.metadata["build_options"]["test"]["depth_resampling"] == "demon"


def test_sparse_readings_lost_by_demons_resampling_are_counted(tmp_path, rng):
    views = demon_files.moving_views(rng, 2, 2 * HEIGHT, 2 * WIDTH)
    sparse = np.zeros_like(views[0]["depth"])
    sparse[101, 333] = 4.5  # DeMoN's rule samples even rows and columns only
    views[0] = dict(views[0], depth=sparse)
    path = write_file(tmp_path / "custom_test.h5", [("s", views)])
    counts = {}
    for resampling in ("demon", "centred"):
        report = pairs.BuildReport("test")
        ((_, example),) = pairs.generate([path], "test", depth_resampling=resampling, report=report)
        counts[resampling] = (np.count_nonzero(example["depth1"]), report.as_dict())
    assert counts["demon"][0] == 0 and counts["centred"][0] == 1
    assert counts["demon"][1]["no_valid_depth_written"] == 1
    assert counts["demon"][1]["files"]["custom_test.h5"]["no_valid_depth_written"] == 1
    assert counts["centred"][1]["no_valid_depth_written"] == 0
    report = pairs.BuildReport("test")
    list(pairs.generate([path], "test", report=report))
    assert "1 written pairs have no valid depth in view 1 after resampling" in report.format()
    assert "depth_resampling=centred keeps them" in report.format()


def test_this_protocol_is_a_new_version_never_read_from_an_older_build(tmp_path):
    builder = data.get_builder("demon/custom", tmp_path)
    assert str(builder.version) == "2.0.0" == data.version("demon/sun3d")
    assert builder.data_path.name == "2.0.0"
    notes = builder.info.release_notes["2.0.0"]
    for change in ("image_decoder=demon", "DeMoN's order", "DeMoN's depth resampling"):
        assert change in notes
