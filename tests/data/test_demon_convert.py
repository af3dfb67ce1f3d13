"""Tests of data/demon/convert.py: recording folder -> DeMoN file -> builder -> records."""

from __future__ import annotations

import subprocess
import sys

import cv2
import demon_files
import numpy as np
import pytest

import data
from data.demon import convert, reader
from gld import records

HEIGHT, WIDTH = 192, 256
FX, FY, CX, CY = 230.0, 228.0, 127.0, 95.5  # OpenCV convention: pixel (0, 0) centred at 0


def quaternion_xyzw(axis, degrees):
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    half = np.radians(degrees) / 2
    return [*(np.sin(half) * axis), np.cos(half)]


def camera_to_world_poses(count):
    """[N, 4, 4] camera-to-world poses written out from axis-angle (independent of quaternions)."""
    poses = np.tile(np.eye(4), (count, 1, 1))
    for index in range(count):
        poses[index, :3, :3] = demon_files.rotation_about([0.2, 1.0, 0.1], 4.0 * index + 1.0)
        poses[index, :3, 3] = [0.15 * index + 0.1, 0.02 * index, -0.05 * index + 1.0]
    return poses


def write_recording(folder, count, rng, *, timestamps=True, dense=True, ray_length=False):
    """Images, TUM trajectory and depth (PNG folder or sparse CSV) of a tiny recording."""
    (folder / "rgb").mkdir(parents=True)
    poses = camera_to_world_poses(count)
    names = [
        f"{100 + 0.1 * index:.6f}" if timestamps else f"frame{index:03d}" for index in range(count)
    ]
    images, depths = [], []
    lines = ["# timestamp tx ty tz qx qy qz qw"]
    for index, name in enumerate(names):
        image = demon_files.texture(rng, HEIGHT, WIDTH)
        cv2.imwrite(str(folder / "rgb" / f"{name}.png"), cv2.cvtColor(image, cv2.COLOR_RGB2BGR))
        images.append(image)
        angle = 4.0 * index + 1.0
        position = poses[index, :3, 3]
        quaternion = quaternion_xyzw([0.2, 1.0, 0.1], angle)
        lines.append(
            f"{100 + 0.1 * index + 0.003:.6f} " + " ".join(map(str, [*position, *quaternion]))
        )
        depths.append(rng.integers(1500, 4000, size=(HEIGHT, WIDTH)).astype(np.uint16))
    (folder / "trajectory.txt").write_text("\n".join(lines) + "\n")
    if dense:
        (folder / "depth").mkdir()
        for name, depth in zip(names, depths, strict=True):
            depths_with_hole = depth.copy()
            depths_with_hole[:5, :7] = 0  # no reading
            cv2.imwrite(str(folder / "depth" / f"{name}.png"), depths_with_hole)
    return names, images, poses


def test_tum_and_dense_depth_round_trip(tmp_path):
    rng = np.random.default_rng(3)
    names, images, poses = write_recording(tmp_path / "rec", 4, rng)
    result = convert.convert(
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
    names, images, poses = write_recording(tmp_path / "rec", 4, rng, timestamps=False, dense=False)
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
    result = convert.convert(
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


def test_quaternions_follow_tum_convention():
    # 90 degrees about z maps x to y.
    rotation = convert.quaternion_to_rotation(np.array(quaternion_xyzw([0, 0, 1], 90.0)))
    np.testing.assert_allclose(rotation @ [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], atol=1e-12)
    random_rotation = demon_files.rotation_about([0.3, -0.2, 0.9], 37.0)
    quaternion = quaternion_xyzw([0.3, -0.2, 0.9], 37.0)
    np.testing.assert_allclose(
        convert.quaternion_to_rotation(np.array(quaternion)), random_rotation
    )


def test_pairs_by_frame_gap_and_baseline():
    centres = np.array([[0.0, 0, 0], [0.05, 0, 0], [0.12, 0, 0], [0.3, 0, 0], [0.31, 0, 0]])
    assert convert.select_pairs(centres, frame_gap=2) == [(0, 2), (1, 3), (2, 4)]
    assert convert.select_pairs(centres, min_baseline=0.1, max_baseline=0.2) == [(0, 2), (2, 3)]
    assert convert.select_pairs(centres, min_baseline=0.1, max_baseline=0.2, max_frame_gap=1) == [
        (2, 3)
    ]


def test_user_mistakes_name_the_input(tmp_path):
    rng = np.random.default_rng(1)
    write_recording(tmp_path / "rec", 3, rng, timestamps=False)
    (tmp_path / "rec" / "two_poses.txt").write_text("\n".join("0 0 0 0 0 0 0 1" for _ in range(2)))
    with pytest.raises(ValueError, match="3 images but 2 poses"):
        convert.convert(
            tmp_path / "rec" / "rgb",
            tmp_path / "rec" / "two_poses.txt",
            "1,1,1,1",
            tmp_path,
            depth=tmp_path / "rec" / "depth",
        )
    (tmp_path / "bad.csv").write_text("frame,u,v,depth\nframe999,1,1,2.0\n")
    with pytest.raises(ValueError, match=r"bad.csv:2: frame 'frame999'"):
        convert.read_sparse_depth(tmp_path / "bad.csv", [tmp_path / "frame000.png"], (4, 4), 1.0)
    with pytest.raises(ValueError, match="intrinsics"):
        convert.read_intrinsics("1,2,3")


def test_command_line_writes_the_file(tmp_path):
    write_recording(tmp_path / "rec", 3, np.random.default_rng(2))
    command = [
        sys.executable,
        "-m",
        "data.demon.convert",
        f"--images={tmp_path / 'rec' / 'rgb'}",
        f"--poses={tmp_path / 'rec' / 'trajectory.txt'}",
        f"--intrinsics={FX},{FY},{CX},{CY}",
        f"--depth={tmp_path / 'rec' / 'depth'}",
        "--depth_scale=0.001",
        f"--output_dir={tmp_path / 'out'}",
        "--recording=lab",
    ]
    completed = subprocess.run(
        command, capture_output=True, text=True, cwd=data.__path__[0] + "/.."
    )
    assert completed.returncode == 0, completed.stderr
    assert "custom_train_lab.h5: 2 pairs (train)" in completed.stdout
    with reader.DemonFile(tmp_path / "out" / "custom_train_lab.h5") as demon_file:
        assert len(demon_file.groups()) == 2
