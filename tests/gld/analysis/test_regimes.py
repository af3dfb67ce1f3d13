"""`gld.analysis.regimes`: per-pair properties on hand-made pairs, bins, summaries, the table and
the figure."""

import numpy as np
import pytest

from gld import geometry
from gld.analysis import regimes

HEIGHT, WIDTH = 48, 64
INTRINSICS = np.array([0.8, 1.0667, 0.5, 0.5])


def _pair(rotation, translation, *, seed=0):
    """A rigid pair seen with INTRINSICS: depth 2-6 with structure, its exact flow as both
    the true and the estimated flow, every pixel valid."""
    rng = np.random.default_rng(seed)
    v, u = np.mgrid[0:HEIGHT, 0:WIDTH]
    depth = 4.0 + 1.5 * np.sin(u / 7.0) * np.cos(v / 5.0) + 0.3 * rng.random((HEIGHT, WIDTH))
    camera_matrix = geometry.intrinsics_matrix(INTRINSICS, HEIGHT, WIDTH)
    flow, _ = geometry.depth_to_flow(
        depth, camera_matrix, camera_matrix, np.asarray(rotation), np.asarray(translation)
    )
    return {
        "flow": flow.astype(np.float32),
        "gt_flow": flow.astype(np.float32),
        "gt_flow_valid": np.ones((HEIGHT, WIDTH), bool),
        "depth": depth.astype(np.float32),
        "depth_valid": np.ones((HEIGHT, WIDTH), bool),
        "intrinsics1": INTRINSICS.astype(np.float32),
        "intrinsics2": INTRINSICS.astype(np.float32),
        "rotation": np.asarray(rotation, np.float32),
        "translation": np.asarray(translation, np.float32),
    }


ROTATION = geometry.rotation_matrix(np.radians([1.0, -2.0, 0.5]))
TRANSLATION = np.array([0.2, -0.05, 0.1])


def test_rotation_share_is_one_for_a_pure_rotation_and_zero_for_a_pure_translation():
    assert regimes.rotation_share(_pair(ROTATION, np.zeros(3))) == pytest.approx(1.0, abs=1e-5)
    assert regimes.rotation_share(_pair(np.eye(3), TRANSLATION)) == pytest.approx(0.0, abs=1e-6)
    both = regimes.rotation_share(_pair(ROTATION, TRANSLATION))
    assert 0.05 < both < 1.5


def test_rotation_share_reads_the_valid_pixels_only_and_is_nan_without_any():
    pair = _pair(ROTATION, np.zeros(3))
    pair["gt_flow_valid"][:, WIDTH // 2 :] = False
    pair["gt_flow"][:, WIDTH // 2 :] = 1000.0
    assert regimes.rotation_share(pair) == pytest.approx(1.0, abs=1e-5)
    pair["gt_flow_valid"][:] = False
    assert np.isnan(regimes.rotation_share(pair))


def test_pair_properties_of_a_hand_made_pair():
    pair = _pair(ROTATION, np.array([0.3, 0.0, 0.4]))
    # The estimated flow is off by (3, 4) px on the valid pixels; far off elsewhere.
    pair["flow"] = pair["gt_flow"] + np.array([3.0, 4.0], np.float32)
    pair["gt_flow_valid"][:4] = False
    pair["flow"][:4] += 100.0
    # The estimate: rotated 2 degrees more about z, translation direction 90 degrees off.
    estimated_rotation = geometry.rotation_matrix(np.radians([0.0, 0.0, 2.0])) @ ROTATION
    estimated_translation = np.array([0.0, 1.0, 0.0])
    properties = regimes.pair_properties(pair, (estimated_rotation, estimated_translation, True))
    assert properties["baseline"] == pytest.approx(0.5, rel=1e-6)
    assert properties["flow_epe_px"] == pytest.approx(5.0, rel=1e-5)
    assert properties["sfm_rotation_error_deg"] == pytest.approx(2.0, abs=1e-3)
    assert properties["sfm_translation_error_deg"] == pytest.approx(90.0, abs=1e-3)
    assert properties["sfm_failed"] == 0.0
    assert properties["rotation_share"] == pytest.approx(regimes.rotation_share(pair))
    assert set(regimes.PROPERTIES) <= set(properties)


def test_a_failed_pose_has_no_error_and_is_counted():
    pair = _pair(ROTATION, TRANSLATION)
    properties = regimes.pair_properties(pair, (np.eye(3), np.zeros(3), False))
    assert np.isnan(properties["sfm_rotation_error_deg"])
    assert np.isnan(properties["sfm_translation_error_deg"])
    assert properties["sfm_failed"] == 1.0


def test_sfm_flow_pose_recovers_the_pose_of_exact_flow():
    pair = _pair(ROTATION, TRANSLATION)
    rotation, translation, succeeded = regimes.sfm_flow_pose(pair)
    assert succeeded
    properties = regimes.pair_properties(pair, (rotation, translation, succeeded))
    assert properties["sfm_rotation_error_deg"] < 0.2
    assert properties["sfm_translation_error_deg"] < 2.0


def test_dominant_texture_counts_valid_pixels_only():
    names = ("plain", "checker", "stripes")
    kinds = np.zeros((4, 5), np.int8)
    kinds[:, :2] = 1  # 8 checker pixels, 12 plain
    valid = np.ones((4, 5), bool)
    assert regimes.dominant_texture(kinds, valid, names) == ("plain", pytest.approx(0.6))
    valid[:, 3:] = False  # 8 checker, 4 plain
    assert regimes.dominant_texture(kinds, valid, names) == ("checker", pytest.approx(8 / 12))
    kinds[:, 2] = 2
    valid[:] = False
    valid[:, 1:3] = True  # 4 checker, 4 stripes: the first kind wins a tie
    assert regimes.dominant_texture(kinds, valid, names) == ("checker", pytest.approx(0.5))
    name, share = regimes.dominant_texture(kinds, np.zeros((4, 5), bool), names)
    assert name == "none" and np.isnan(share)


def test_dominant_texture_refuses_bad_maps():
    with pytest.raises(ValueError, match="one shape"):
        regimes.dominant_texture(np.zeros((4, 5)), np.ones((5, 4), bool), ("plain",))
    with pytest.raises(ValueError, match="indices"):
        regimes.dominant_texture(np.full((2, 2), 3), np.ones((2, 2), bool), ("plain", "noise"))


def test_quantile_bins_put_known_values_in_known_bins():
    values = np.array([9.0, 1.0, 5.0, np.nan, 3.0, 7.0, 2.0, 8.0, 4.0, 6.0])
    labels, edges = regimes.quantile_bins(values, 3)
    np.testing.assert_allclose(edges, [1.0, 11 / 3, 19 / 3, 9.0])
    bins = {value: label.split(":")[0] for value, label in zip(values, labels, strict=True)}
    assert [bins[v] for v in (1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0, 8.0, 9.0)] == list("111222333")
    assert labels[3] == "n/a"
    assert labels[0] == "3: [6.33, 9]" and labels[1] == "1: [1, 3.67)"
    single, single_edges = regimes.quantile_bins(values, 1)
    assert set(single) == {"1: [1, 9]", "n/a"} and len(single_edges) == 2
    none, _ = regimes.quantile_bins(np.array([np.nan, np.inf]), 3)
    assert none == ["n/a", "n/a"]
    with pytest.raises(ValueError, match="num_bins"):
        regimes.quantile_bins(values, 0)


def test_summarise_bins_means_ratio_and_wins():
    labels = ["b", "a", "a", "b", "b", "b"]
    model = np.array([2.0, 1.0, 3.0, 2.0, 5.0, 1.0])
    reference = np.array([1.0, 2.0, 2.0, 1.0, 4.0, 1.0])
    rows = {row.label: row for row in regimes.summarise_bins(labels, model, reference)}
    assert list(rows) == ["a", "b", "all"]
    assert rows["a"] == regimes.BinSummary("a", 2, 2.0, 2.0, 1.0, 0.5)
    # b: the model is never strictly below (a tie is no win).
    assert rows["b"] == regimes.BinSummary("b", 4, 2.5, 1.75, 2.5 / 1.75, 0.0)
    assert rows["all"].pairs == 6 and rows["all"].model_wins == pytest.approx(1 / 6)
    assert rows["all"].ratio == pytest.approx(14 / 11)
    with pytest.raises(ValueError, match="alike"):
        regimes.summarise_bins(labels[:-1], model, reference)


def test_rank_correlation():
    values = np.array([1.0, 2.0, 3.0, 4.0, np.nan])
    assert regimes.rank_correlation(values, np.exp(values)) == pytest.approx(1.0)
    assert regimes.rank_correlation(values, -(values**3)) == pytest.approx(-1.0)
    # Ties get their mean rank: ranks (1, 2.5, 2.5, 4) against (1, 2, 3, 4).
    expected = 4.5 / np.sqrt(4.5 * 5.0)
    assert regimes.rank_correlation([1, 2, 2, 3], [1, 2, 3, 4]) == pytest.approx(expected)
    assert np.isnan(regimes.rank_correlation([1, 1, 1, 1], [1, 2, 3, 4]))
    assert np.isnan(regimes.rank_correlation([1, 2], [1, 2]))


def test_markdown_summary_is_one_well_formed_table():
    labels, _ = regimes.quantile_bins(np.array([0.1, 0.2, 0.3, 0.4]), 2)
    model, reference = np.array([1.0, 1.0, 3.0, 1.0]), np.array([2.0, 2.0, 1.0, 2.0])
    tables = {
        "baseline": regimes.summarise_bins(labels, model, reference),
        "texture_kind": regimes.summarise_bins(["plain"] * 4, model, reference),
    }
    text = regimes.markdown_summary(
        tables, model="net", reference="sfm", correlations={"baseline": 0.25}, title="# t"
    )
    table = [line for line in text.splitlines() if line.startswith("|")]
    assert len({line.count("|") for line in table}) == 1  # no cell breaks its row
    assert "| net Abs-Inv | sfm Abs-Inv | net ÷ sfm | net wins |" in table[0]
    assert table[2] == "| all pairs |  | all | 4 | 1.5000 | 1.7500 | 0.86× | 75% |"
    assert table[3].startswith(f"| {regimes.PROPERTIES['baseline']} | +0.25 | 1: [0.1, 0.25) |")
    assert table[3].endswith("| 2 | 1.0000 | 2.0000 | 0.50× | 100% |")
    assert table[4].endswith("| 2 | 2.0000 | 1.5000 | 1.33× | 50% |")
    assert table[5].startswith("| texture kind |  | plain | 4 |")
    assert text.startswith("# t\n")
    assert sum(line.startswith("| all pairs") for line in table) == 1


def test_draw_regimes_writes_a_png(tmp_path):
    rng = np.random.default_rng(0)
    properties = {name: rng.random(12) for name in regimes.PROPERTIES}
    ratios = np.exp(rng.normal(size=12))
    kinds = ["plain", "noise", "checker"] * 4
    for name, categories in (("with.png", kinds), ("without.png", None)):
        path = regimes.draw_regimes(
            tmp_path / name,
            properties,
            ratios,
            edges={"baseline": [0, 0.5, 1]},
            categories=categories,
        )
        assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
