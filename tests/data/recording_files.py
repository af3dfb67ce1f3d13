"""Writes a tiny robot recording for the converter's tests: images, TUM trajectory, depth.

Poses are written from axis-angle rotations (`demon_files.rotation_about`), independently
of `data.demon.recordings`' quaternion reader.
"""

from __future__ import annotations

import cv2
import demon_files
import numpy as np

HEIGHT, WIDTH = 192, 256
FX, FY, CX, CY = 230.0, 228.0, 127.0, 95.5  # OpenCV convention: pixel (0, 0) centred at 0


def quaternion_xyzw(axis, degrees):
    """[qx, qy, qz, qw] of the rotation by `degrees` about `axis` (TUM's order)."""
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


def make_recording(
    folder, count, rng, *, timestamps=True, dense=True, ray_length=False, numbered=False
):
    """Images, TUM trajectory (stamped 100.003 s, 100.103 s, ...) and depth (PNG folder or
    sparse CSV) of a tiny recording; images named by time stamp (`timestamps`), by frame
    number (`numbered`: 000000, 000001, ...) or frame000, frame001, ..."""
    (folder / "rgb").mkdir(parents=True)
    poses = camera_to_world_poses(count)
    if numbered:
        names = [f"{index:06d}" for index in range(count)]
    elif timestamps:
        names = [f"{100 + 0.1 * index:.6f}" for index in range(count)]
    else:
        names = [f"frame{index:03d}" for index in range(count)]
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
