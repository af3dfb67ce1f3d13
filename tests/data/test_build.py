import os
import subprocess
import sys

from conftest import REPO_ROOT


def _build(*args):
    env = dict(os.environ, JAX_PLATFORMS="cpu", PYTHONPATH=str(REPO_ROOT))
    return subprocess.run(
        [sys.executable, "-m", "data.build", *args],
        capture_output=True,
        text=True,
        env=env,
        cwd=REPO_ROOT,
        timeout=300,
    )


def test_build_command_builds_and_reports(tmp_path):
    result = _build("--dataset=gld_scenes/tiny", f"--data_dir={tmp_path}", "--workers=2")
    assert result.returncode == 0, result.stderr[-2000:]
    assert "gld_scenes/tiny train: 32 pairs" in result.stdout
    assert "gld_scenes/tiny test: 16 pairs" in result.stdout
    assert list((tmp_path / "gld_scenes" / "tiny").glob("*/*.array_record*"))


def test_build_command_lists_valid_configs_for_an_unknown_one(tmp_path):
    result = _build("--dataset=gld_scenes/huge", f"--data_dir={tmp_path}")
    assert result.returncode != 0
    assert "gld_scenes/tiny" in result.stderr and "gld_scenes/small" in result.stderr
