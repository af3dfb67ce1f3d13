"""A rigid two-view scene for the geometry tests: random depth, the flow it gives under a
pose, the cameras and the pose."""

import numpy as np

from gld import geometry

HEIGHT, WIDTH = 24, 32
# Normalised intrinsics of the two cameras (they differ).
INTRINSICS = np.array([[0.9, 1.2, 0.52, 0.47], [1.1, 1.4, 0.5, 0.5]], np.float32)


def two_view_scene(translation, rotation_vector=(0.02, -0.04, 0.01), seed=0):
    """(depth [H, W] in [1, 5], flow [H, W, 2], camera1, camera2, rotation, translation),
    float64; every pixel lands in front of camera 2."""
    rng = np.random.default_rng(seed)
    camera1, camera2 = (geometry.intrinsics_matrix(k, HEIGHT, WIDTH) for k in INTRINSICS)
    depth = rng.uniform(1.0, 5.0, (HEIGHT, WIDTH))
    rotation = geometry.rotation_matrix(np.array(rotation_vector, np.float64))
    translation = np.asarray(translation, np.float64)
    flow, valid = geometry.depth_to_flow(depth, camera1, camera2, rotation, translation)
    assert valid.all()
    return depth, flow, camera1, camera2, rotation, translation
