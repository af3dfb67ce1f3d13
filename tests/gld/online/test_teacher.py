"""The classical teacher's labels: the depth a pair's own flow gives where it gives it well."""

import numpy as np
import pytest

from gld import geometry
from gld.online import teacher
from gld.online.teacher import TeacherSettings

HEIGHT, WIDTH = 96, 128
INTRINSICS = np.array([0.8, 1.0, 0.5, 0.5], np.float32)


def _pair(translation_metres, near=1.0, far=4.0):
    """A rigid scene (a slanted floor of depth `near` to `far` metres, with a bump) seen
    from two poses: the example's flow (exact) and intrinsics, the true depth, the
    motion's length in metres and its rotation."""
    rows = np.linspace(0.0, 1.0, HEIGHT)[:, None]
    columns = np.linspace(0.0, 1.0, WIDTH)[None]
    depth = far - (far - near) * rows + 0.3 * np.sin(6 * columns) * rows
    rotation = geometry.rotation_matrix(np.radians([1.0, -2.0, 0.5]))
    translation = np.asarray(translation_metres, np.float64)
    # Exact everywhere (a pixel that leaves view 2 still has its flow).
    flow, _ = geometry.ground_truth_flow(depth, None, INTRINSICS, INTRINSICS, rotation, translation)
    example = {"flow": flow, "intrinsics1": INTRINSICS, "intrinsics2": INTRINSICS}
    return example, depth, float(np.linalg.norm(translation)), rotation


def _parallax(example, depth, rotation):
    camera = geometry.intrinsics_matrix(INTRINSICS.astype(np.float64), HEIGHT, WIDTH)
    rotation_only = geometry.rotation_flow(rotation, camera, camera, HEIGHT, WIDTH)
    return np.linalg.norm(example["flow"] - rotation_only, axis=-1)


@pytest.mark.parametrize("motion", [[0.02, 0.0, 0.1], [0.1, 0.01, 0.02]], ids=["forward", "side"])
def test_on_exact_flow_the_labels_are_the_true_depth_where_the_parallax_is_large(motion):
    example, depth, baseline, rotation = _pair(motion)
    settings = TeacherSettings(count=50, min_parallax=1.5)
    labels = teacher.classical_labels(example, baseline, settings, np.random.default_rng(0))
    assert len(labels) == 50
    rows, columns = labels[:, 0].astype(int), labels[:, 1].astype(int)
    assert len(set(zip(rows, columns, strict=True))) == 50  # distinct pixels
    # In baselines: the metres over the motion's length.
    np.testing.assert_allclose(labels[:, 2] * baseline, depth[rows, columns], rtol=1e-3)
    assert (_parallax(example, depth, rotation)[rows, columns] >= 1.5 - 1e-3).all()


def test_only_pixels_with_the_parallax_asked_for_are_labelled():
    example, depth, baseline, rotation = _pair([0.02, 0.0, 0.1])
    parallax = _parallax(example, depth, rotation)
    threshold = float(np.quantile(parallax, 0.9))  # the tenth of the pixels with the most
    everything = TeacherSettings(count=HEIGHT * WIDTH, min_parallax=threshold)
    labels = teacher.classical_labels(example, baseline, everything, np.random.default_rng(0))
    expected = np.mean(parallax >= threshold) * HEIGHT * WIDTH
    assert abs(len(labels) - expected) <= 0.02 * HEIGHT * WIDTH


def test_a_surface_nearer_than_the_nearest_depth_is_left_out():
    example, depth, baseline, _ = _pair([0.1, 0.01, 0.02], near=0.5, far=4.0)
    settings = TeacherSettings(count=HEIGHT * WIDTH, min_parallax=0.5, min_depth=1.0)
    labels = teacher.classical_labels(example, baseline, settings, np.random.default_rng(0))
    assert len(labels) > 0
    assert (labels[:, 2] * baseline >= 1.0 - 1e-3).all()
    assert (depth < 0.99).sum() > 0  # there were nearer pixels to leave out


def test_the_draw_is_the_generators_and_a_failed_pose_gives_no_label():
    example, _, baseline, _ = _pair([0.1, 0.01, 0.02])
    settings = TeacherSettings(count=20)

    def draw(seed):
        return teacher.classical_labels(example, baseline, settings, np.random.default_rng(seed))

    np.testing.assert_array_equal(draw(3), draw(3))
    assert not np.array_equal(draw(3), draw(4))
    still = {**example, "flow": np.zeros_like(example["flow"])}  # no motion: no pose
    assert len(teacher.classical_labels(still, baseline, settings, np.random.default_rng(0))) == 0


@pytest.mark.parametrize(
    "changes", [{"count": -1}, {"min_parallax": 0.0}, {"max_epipolar": -1.0}, {"min_depth": 0.0}]
)
def test_bad_teacher_settings_are_refused(changes):
    with pytest.raises(ValueError, match=next(iter(changes))):
        TeacherSettings(**changes)
