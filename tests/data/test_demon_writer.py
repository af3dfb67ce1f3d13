"""Tests of data/demon/writer.py: recording folder -> DeMoN file -> builder -> records."""

from __future__ import annotations

import re
from pathlib import Path

import cv2
import numpy as np
import pytest
from recording_files import CX, CY, FX, FY, HEIGHT, WIDTH, make_recording

import data
from data.demon import reader, recordings, writer
from gld import records
from gld.arguments import ArgumentError
from gld.inference import recordings as inference_recordings


def test_tum_and_dense_depth_round_trip(tmp_path):
    rng = np.random.default_rng(3)
    names, images, poses = make_recording(tmp_path / "rec", 4, rng)
    result = writer.write_recording(
        tmp_path / "rec" / "rgb",
        tmp_path / "rec" / "trajectory.txt",
        f"{FX},{FY},{CX},{CY}",
        tmp_path / "out",
        depth=tmp_path / "rec" / "depth",
        depth_scale=0.001,
    )
    assert result["pairs"] == {"train": 3}
    path = tmp_path / "out" / "custom_train.h5"
    assert result["files"]["train"] == path
    with reader.DemonFile(path) as demon_file:
        assert demon_file.groups() == [f"{names[i]}__{names[i + 1]}" for i in range(3)]
        group = demon_file.groups()[1]
        assert demon_file.pairs(group, "test") == [(0, 1)]
        for view_index, frame in enumerate((1, 2)):
            view = demon_file.view(group, view_index)
            np.testing.assert_array_equal(view.image, images[frame])  # lossless WebP
            png = cv2.imread(str(tmp_path / "rec" / "depth" / f"{names[frame]}.png"), -1)
            np.testing.assert_allclose(view.depth, png * 0.001, rtol=1e-3)
            assert np.all(view.depth[:5, :7] == 0)
            # Pixel-index principal point + half a pixel, over the image size.
            np.testing.assert_allclose(
                view.intrinsics, [FX / WIDTH, FY / HEIGHT, (CX + 0.5) / WIDTH, (CY + 0.5) / HEIGHT]
            )
            # World-to-camera: the camera centre maps to 0, the camera's axes to the identity.
            rotation_c2w, centre = poses[frame, :3, :3], poses[frame, :3, 3]
            np.testing.assert_allclose(view.rotation @ centre + view.translation, 0, atol=1e-9)
            np.testing.assert_allclose(view.rotation @ rotation_c2w, np.eye(3), atol=1e-9)


def test_sparse_ray_length_readings_build_with_custom_config(tmp_path):
    rng = np.random.default_rng(5)
    names, images, poses = make_recording(tmp_path / "rec", 4, rng, timestamps=False, dense=False)
    world_to_camera = np.linalg.inv(poses)
    (tmp_path / "rec" / "poses.txt").write_text(
        "\n".join(" ".join(map(str, matrix.reshape(-1))) for matrix in world_to_camera)
    )
    # One range reading per frame along the ray through pixel (u, v); frames by name or index.
    readings = {0: (40, 30, 2.5), 1: (200, 150, 3.0), 2: (128, 96, 4.0), 3: (10, 180, 1.5)}
    rows = ["frame,u,v,depth"] + [
        f"{names[f] if f % 2 else f},{u},{v},{r}" for f, (u, v, r) in readings.items()
    ]
    (tmp_path / "rec" / "range.csv").write_text("\n".join(rows) + "\n")
    result = writer.write_recording(
        tmp_path / "rec" / "rgb",
        tmp_path / "rec" / "poses.txt",
        f"{FX},{FY},{CX},{CY}",
        tmp_path / "manual",
        depth=tmp_path / "rec" / "range.csv",
        pose_format="matrix",
        pose_direction="world_to_camera",
        depth_metric="ray_length",
        test_fraction=0.5,
    )
    # Frames 0-1 train, 2-3 test; the pair 1-2 would put a test frame in training.
    assert result["pairs"] == {"train": 1, "test": 1}
    assert result["dropped"] == {"crosses_split_boundary": 1}

    builder = data.prepare("demon/custom", tmp_path / "datasets", tmp_path / "manual")
    assert sorted(builder.info.splits) == ["test", "train"]
    for split, (first, second) in (("train", (0, 1)), ("test", (2, 3))):
        (example,) = [records.decode(r) for r in builder.as_data_source(split=split)]
        assert example["id"] == f"custom_{split}.h5/{names[first]}__{names[second]}/0-1"
        np.testing.assert_array_equal(example["image1"], images[first])
        np.testing.assert_array_equal(example["image2"], images[second])
        # The single reading: camera z = ray length / |K^-1 (u, v, 1)|, at its own pixel.
        u, v, ray_length = readings[first]
        ray = np.linalg.inv([[FX, 0, CX], [0, FY, CY], [0, 0, 1]]) @ [u, v, 1.0]
        assert np.count_nonzero(example["depth1"]) == 1
        assert example["depth1"][v, u] == pytest.approx(ray_length / np.linalg.norm(ray), rel=1e-3)
        relative = world_to_camera[second] @ np.linalg.inv(world_to_camera[first])
        np.testing.assert_allclose(example["rotation"], relative[:3, :3], atol=1e-6)
        np.testing.assert_allclose(example["translation"], relative[:3, 3], atol=1e-6)
        np.testing.assert_allclose(
            example["intrinsics1"],
            [FX / WIDTH, FY / HEIGHT, (CX + 0.5) / WIDTH, (CY + 0.5) / HEIGHT],
        )


def test_pose_count_mismatch_names_the_input(tmp_path):
    rng = np.random.default_rng(1)
    make_recording(tmp_path / "rec", 3, rng, timestamps=False)
    (tmp_path / "rec" / "two_poses.txt").write_text("\n".join("0 0 0 0 0 0 0 1" for _ in range(2)))
    with pytest.raises(ValueError, match="3 images but 2 poses"):
        writer.write_recording(
            tmp_path / "rec" / "rgb",
            tmp_path / "rec" / "two_poses.txt",
            "1,1,1,1",
            tmp_path,
            depth=tmp_path / "rec" / "depth",
        )


def _convert(tmp_path, output_dir, source="rec", **options):
    """`write_recording` of the recording in tmp_path/<source> (TUM poses, dense depth)."""
    return writer.write_recording(
        tmp_path / source / "rgb",
        tmp_path / source / "trajectory.txt",
        f"{FX},{FY},{CX},{CY}",
        output_dir,
        depth=tmp_path / source / "depth",
        depth_scale=0.001,
        **options,
    )


def _files(folder):
    """Every file under `folder`, hidden ones included."""
    return sorted(path.relative_to(folder) for path in folder.rglob("*") if path.is_file())


def test_existing_output_is_replaced_only_with_overwrite(tmp_path):
    names, _, _ = make_recording(tmp_path / "rec", 4, np.random.default_rng(4))
    out = tmp_path / "out"
    assert _convert(tmp_path, out)["pairs"] == {"train": 3}
    written = (out / "custom_train.h5").read_bytes()
    with pytest.raises(FileExistsError, match=r"custom_train.h5 already exist.*--overwrite"):
        _convert(tmp_path, out, frame_gap=2)
    assert (out / "custom_train.h5").read_bytes() == written
    assert _convert(tmp_path, out, frame_gap=2, overwrite=True)["pairs"] == {"train": 2}
    with reader.DemonFile(out / "custom_train.h5") as demon_file:
        assert demon_file.groups() == [f"{names[0]}__{names[2]}", f"{names[1]}__{names[3]}"]
    assert _files(out) == [Path("custom_train.h5")]  # no temporary file left


def test_failed_or_empty_run_writes_nothing(tmp_path):
    names, _, _ = make_recording(tmp_path / "rec", 4, np.random.default_rng(6))
    out = tmp_path / "out"
    _convert(tmp_path, out, test_fraction=0.5)
    before = {path: (out / path).read_bytes() for path in _files(out)}
    assert sorted(before) == [Path("custom_test.h5"), Path("custom_train.h5")]

    # Frame 3 has another size: found while writing the test split, after the train one.
    smaller = np.zeros((HEIGHT // 2, WIDTH // 2, 3), np.uint8)
    cv2.imwrite(str(tmp_path / "rec" / "rgb" / f"{names[3]}.png"), smaller)
    with pytest.raises(ValueError, match="all images need one size"):
        _convert(tmp_path, out, test_fraction=0.5, overwrite=True)
    assert {path: (out / path).read_bytes() for path in _files(out)} == before
    with pytest.raises(ValueError, match="all images need one size"):
        _convert(tmp_path, tmp_path / "fresh", test_fraction=0.5)
    assert not (tmp_path / "fresh").exists()

    # No pair at all (gap too large), or none with a depth reading in both frames.
    with pytest.raises(ValueError, match="4 frames give no train pairs"):
        _convert(tmp_path, out, frame_gap=4, overwrite=True)
    for name in names:
        cv2.imwrite(str(tmp_path / "rec" / "depth" / f"{name}.png"), np.zeros((4, 4), np.uint16))
    with pytest.raises(ValueError, match="no train pair has a depth reading"):
        _convert(tmp_path, out, frame_gap=2, overwrite=True)
    assert {path: (out / path).read_bytes() for path in _files(out)} == before


def test_recording_name_stays_inside_the_output_folder(tmp_path):
    make_recording(tmp_path / "rec", 3, np.random.default_rng(8))
    for name in ("x/../../../name", "..", ".hidden", "a\\b"):
        with pytest.raises(ValueError, match=f"--recording={name!r}".replace("\\", "\\\\")):
            _convert(tmp_path, tmp_path / "out" / "deep", recording=name)
    assert not list(tmp_path.rglob("*.h5"))
    assert _convert(tmp_path, tmp_path / "out", recording="lab-2.v1")["files"] == {
        "train": tmp_path / "out" / "custom_train_lab-2.v1.h5"
    }


def test_nan_in_a_pose_line_is_refused_naming_the_line(tmp_path):
    make_recording(tmp_path / "rec", 3, np.random.default_rng(9))
    trajectory = tmp_path / "rec" / "trajectory.txt"
    lines = trajectory.read_text().splitlines()
    lines[2] = " ".join(["nan" if i == 2 else value for i, value in enumerate(lines[2].split())])
    trajectory.write_text("\n".join(lines) + "\n")
    with pytest.raises(ValueError, match=r"trajectory.txt:3: NaN or infinite value"):
        _convert(tmp_path, tmp_path / "out")
    assert not (tmp_path / "out").exists()


def test_reconverting_a_recording_replaces_all_of_its_files(tmp_path):
    make_recording(tmp_path / "rec", 6, np.random.default_rng(8))
    out = tmp_path / "out"
    first = _convert(tmp_path, out, test_fraction=0.5)
    assert sorted(first["files"]) == ["test", "train"] and first["removed"] == []
    # Again without --test_fraction: the old test file holds pairs of the same frames.
    again = _convert(tmp_path, out, overwrite=True)
    assert again["removed"] == [str(out / "custom_test.h5")]
    assert _files(out) == [Path("custom_train.h5")]

    # The other split of the same recording, without --overwrite: refused, nothing written.
    written = (out / "custom_train.h5").read_bytes()
    with pytest.raises(FileExistsError, match=r"custom_train.h5 holds pairs of the same recording"):
        _convert(tmp_path, out, split="test")
    assert _files(out) == [Path("custom_train.h5")]
    assert (out / "custom_train.h5").read_bytes() == written


def test_another_recordings_test_file_stays(tmp_path):
    make_recording(tmp_path / "rec", 4, np.random.default_rng(9))
    make_recording(tmp_path / "other", 4, np.random.default_rng(10))
    out = tmp_path / "out"
    _convert(tmp_path, out, source="other", split="test")
    test_file = (out / "custom_test.h5").read_bytes()
    result = _convert(tmp_path, out, overwrite=True)
    assert result["removed"] == [] and result["pairs"] == {"train": 3}
    assert (out / "custom_test.h5").read_bytes() == test_file


def test_index_named_images_with_timestamped_poses_convert_by_order(tmp_path):
    names, images, poses = make_recording(
        tmp_path / "rec", 3, np.random.default_rng(11), numbered=True
    )
    assert names[0] == "000000"
    # By time (the default tries it: both sides look stamped) frame 0 is 100 s from
    # every pose: refused in one line that names the file and the way out.
    with pytest.raises(ArgumentError) as refused:
        _convert(tmp_path, tmp_path / "out")
    message = str(refused.value)
    assert re.fullmatch(
        r"--match_frames=auto: .*000000\.png is 100\.003 s from the nearest pose's time stamp: "
        r".* --match_frames=order matches the i-th image to the i-th pose",
        message,
    ), message
    assert not (tmp_path / "out").exists()

    result = _convert(tmp_path, tmp_path / "out", match_frames="order")
    assert result["pairs"] == {"train": 2}
    with reader.DemonFile(tmp_path / "out" / "custom_train.h5") as demon_file:
        assert demon_file.groups() == ["000000__000001", "000001__000002"]
        for view_index, frame in enumerate((1, 2)):
            view = demon_file.view("000001__000002", view_index)
            np.testing.assert_array_equal(view.image, images[frame])
            # The i-th pose: its camera centre maps to 0.
            centre = poses[frame, :3, 3]
            np.testing.assert_allclose(view.rotation @ centre + view.translation, 0, atol=1e-9)


def test_a_pair_is_its_first_frames_depth_in_converter_and_predictor(tmp_path):
    """A pair (i, j) takes frame i's reading, in the converter's records and the
    predictor's scale, and is left out without one; the converter also needs one on
    frame j (the reader refuses a view without depth), the predictor does not."""
    names, _, _ = make_recording(tmp_path / "rec", 4, np.random.default_rng(12), dense=False)
    readings = {0: (40, 30, 2.5), 2: (128, 96, 4.0), 3: (10, 180, 1.5)}  # none on frame 1
    ranges = tmp_path / "rec" / "range.csv"
    ranges.write_text(
        "frame,u,v,depth\n"
        + "".join(f"{names[frame]},{u},{v},{r}\n" for frame, (u, v, r) in readings.items())
    )
    converted = writer.write_recording(
        tmp_path / "rec" / "rgb",
        tmp_path / "rec" / "trajectory.txt",
        f"{FX},{FY},{CX},{CY}",
        tmp_path / "out",
        depth=ranges,
    )
    # Pairs (0, 1), (1, 2), (2, 3): frame 1 has no reading.
    assert converted["pairs"] == {"train": 1}
    assert converted["dropped"] == {"no_reading_on_second_frame": 1, "no_reading_on_first_frame": 1}
    with reader.DemonFile(tmp_path / "out" / "custom_train.h5") as demon_file:
        assert demon_file.groups() == [f"{names[2]}__{names[3]}"]
        first_view = demon_file.view(demon_file.groups()[0], 0)
    u, v, depth = readings[2]
    assert np.count_nonzero(first_view.depth) == 1
    assert first_view.depth[v, u] == pytest.approx(depth, rel=1e-3)

    image_paths = recordings.list_images(tmp_path / "rec" / "rgb")
    plan = inference_recordings.plan_recording(
        inference_recordings.frame_pairs(4),
        ranges=inference_recordings.read_range_readings(
            ranges,
            [path.stem for path in image_paths],
            (HEIGHT, WIDTH),
            frame_indices=lambda frames, lines: recordings.reading_frame_indices(
                frames, lines, ranges, image_paths
            ),
        ),
    )
    assert plan.skipped == {"no range reading on the first frame": 1}  # (1, 2), as converted
    assert plan.pairs == [(0, 1), (2, 3)]
    np.testing.assert_allclose(plan.ranges[1], [readings[2]])  # (2, 3) by frame 2's reading
