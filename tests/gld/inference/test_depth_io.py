"""Previews a person can read: the colourised inverse depth with a colour bar in units."""

import cv2
import numpy as np

from gld.inference import depth_io


def _magma(level: int) -> np.ndarray:
    pixel = cv2.applyColorMap(np.full((1, 1), level, np.uint8), cv2.COLORMAP_MAGMA)
    return cv2.cvtColor(pixel, cv2.COLOR_BGR2RGB)[0, 0]


def test_the_colour_bar_runs_from_the_top_inverse_depth_to_far_and_labels_depths():
    bar = depth_io.colour_bar(96, top=0.5, unit="m")
    assert bar.shape[0] == 96
    np.testing.assert_array_equal(bar[0, 0], _magma(255))  # near: 1 / 0.5 = 2 m
    np.testing.assert_array_equal(bar[-1, 0], _magma(0))  # far
    # Ticks at 1, 1/2 and 1/4 of the top inverse depth: 2, 4 and 8 metres.
    assert depth_io.colour_bar_ticks(0.5, "m") == [(0.0, "2 m"), (0.5, "4 m"), (0.75, "8 m")]
    assert depth_io.colour_bar_ticks(0.5, "x baseline")[1] == (0.5, "4 x baseline")


def test_a_preview_is_the_image_the_map_on_its_scale_and_the_bar(tmp_path):
    rng = np.random.default_rng(0)
    image = rng.integers(0, 255, (48, 64, 3), np.uint8)
    depth = rng.uniform(1.0, 5.0, (48, 64)).astype(np.float32)
    depth[0, :5] = np.nan  # no prediction: black
    path = tmp_path / "preview.png"
    depth_io.write_preview(path, image, depth, top=0.8, unit="m")
    panel = cv2.cvtColor(cv2.imread(str(path)), cv2.COLOR_BGR2RGB)
    bar = depth_io.colour_bar(48, 0.8, "m")
    assert panel.shape == (48, 2 * 64 + bar.shape[1], 3)
    np.testing.assert_array_equal(panel[:, :64], image)
    # The map on the given scale: two maps share it, whatever their own range.
    np.testing.assert_array_equal(panel[:, 64:128], depth_io.colourise_inverse_depth(depth, 0.8))
    np.testing.assert_array_equal(panel[0, 64:69], 0)
    np.testing.assert_array_equal(panel[:, 128:], bar)
    # Without a scale, the map's own: its 99th percentile of inverse depth.
    expected = np.percentile(1 / depth[np.isfinite(depth)].astype(np.float64), 99)
    np.testing.assert_allclose(depth_io.inverse_depth_top(depth), expected, rtol=1e-12)


def test_the_colour_bar_has_room_for_its_longest_label():
    """The strip ends in white after every label: none is cut off at the edge."""
    for unit, top in (("m", 0.5), ("x baseline", 0.0171)):
        bar = depth_io.colour_bar(192, top=top, unit=unit)
        np.testing.assert_array_equal(bar[:, -4:], 255)
        labels = [label for _, label in depth_io.colour_bar_ticks(top, unit)]
        assert any(len(label) > 12 for label in labels) == (unit != "m")
    assert (
        depth_io.colour_bar(192, 0.0171, "x baseline").shape[1]
        > depth_io.colour_bar(192, 0.5, "m").shape[1]
    )
