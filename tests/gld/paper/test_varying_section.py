"""Section 5 of the report (varying intrinsics) says which learned models are told the
cameras, from each run's own configuration."""

from report_checks import readme_section, suite_results, write_readme

from gld.paper.sections.varying_intrinsics import reads_cameras

VALUES = {
    "global_local_1px": 0.030,
    "global_local_varying": 0.033,
    "small_encdec_1px": 0.036,
    "small_encdec_varying": 0.037,
}


def test_the_section_says_global_local_reads_each_views_intrinsics(tmp_path):
    results = suite_results(VALUES)
    assert reads_cameras(results["train/global_local_varying"])
    assert not reads_cameras(results["train/small_encdec_varying"])
    assert not reads_cameras(None)
    varying = readme_section(write_readme(tmp_path, results), 5)
    assert "Global-local is told each view's intrinsics" in varying
    assert "Small Enc-Dec is not;" in varying
    assert "The learned models are not told the intrinsics" not in varying


def test_a_global_local_without_the_pose_readers_is_not_told_the_cameras(tmp_path):
    results = suite_results(VALUES)
    config = results["train/global_local_varying"]["config"]["model_config"]
    config.update(derotate_flow=False, parallax_depth=False, pose_refinement_steps=0)
    assert not reads_cameras(results["train/global_local_varying"])
    varying = readme_section(write_readme(tmp_path, results), 5)
    assert "The learned models are not told the intrinsics;" in varying
