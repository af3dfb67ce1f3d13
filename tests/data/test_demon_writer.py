"""Tests of data/demon/writer.py: recording folder -> DeMoN file -> builder -> records."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from recording_files import CX, CY, FX, FY, HEIGHT, WIDTH, make_recording

import data
from data.demon import reader, writer
from gld import records


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
