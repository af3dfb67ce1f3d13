"""A launcher's bad command line, and an error that says what went wrong, end it with one
line on stderr (`data.command_line.run`): exit status 2 for a user's mistake, 1 for a run that
could not go on; a bug keeps its traceback."""

import os
import subprocess
import sys
import textwrap

import pytest
from conftest import REPO_ROOT, launch

# A launcher as every one is written: flags at import, `common.run(main)` at the end.
LAUNCHER = textwrap.dedent(
    """
    import errno, os
    from absl import app, flags
    from experiments import common

    flags.DEFINE_integer("count", 1, "A count.", lower_bound=1)
    flags.DEFINE_string("fail", "", "What main raises.")

    def main(argv):
        from gld.files import DiskFullError
        from gld.runs.lock import WorkdirLockedError

        fail = flags.FLAGS.fail
        if fail == "usage":
            raise app.UsageError("--count: not a count\\nof anything")
        if fail == "held":
            raise WorkdirLockedError("workdir runs/x is in use by another training run")
        if fail == "disk_full":
            raise DiskFullError("disk full: no space left to write in runs/x")
        if fail == "wrapped_disk_full":
            try:
                raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), "runs/x/m.json")
            except OSError as error:
                raise RuntimeError("the background save failed") from error
        if fail == "argument":
            from gld.arguments import ArgumentError
            raise ArgumentError("--split=val: the dataset has only ['test', 'train']")
        if fail == "no_intact_checkpoint":
            from gld.runs.checkpoints import CorruptCheckpointError
            raise CorruptCheckpointError("no checkpoint in runs/x is intact")
        if fail == "nan":
            from gld.training.loop import NonFiniteLossError
            raise NonFiniteLossError("loss is nan at step 7; stopping")
        if fail == "bug":
            raise KeyError("a bug")
        print("ran", flags.FLAGS.count)

    common.run(main)
    """
)


def _launch(*args: str) -> subprocess.CompletedProcess:
    env = dict(os.environ, JAX_PLATFORMS="cpu", PYTHONPATH=str(REPO_ROOT))
    return subprocess.run(
        [sys.executable, "-c", LAUNCHER, *args],
        capture_output=True,
        text=True,
        env=env,
        cwd=REPO_ROOT,
        timeout=120,
    )


def _error(*args: str) -> tuple[int, str, bool]:
    """(exit status, stderr, whether main ran) of the launcher given `args`."""
    result = _launch(*args)
    return result.returncode, result.stderr, "ran" in result.stdout


def test_a_launcher_runs_its_main_with_its_flags_and_a_flagfile(tmp_path):
    flagfile = tmp_path / "good.flags"
    flagfile.write_text("# a comment\n--count=3\n")
    result = _launch(f"--flagfile={flagfile}")
    assert result.returncode == 0, result.stderr
    assert result.stdout == "ran 3\n"


def test_a_flagfile_that_is_not_utf8_is_named_in_one_line(tmp_path):
    bad = tmp_path / "bad.flags"
    bad.write_bytes(b"--count=2\n# caf\xe9 (latin-1)\n")
    line = f"--flagfile={bad}: line 2 is not UTF-8 text (byte 0xe9); save the file as UTF-8"
    assert _error(f"--flagfile={bad}") == (2, line + "\n", False)
    # Named also when another flagfile includes it.
    outer = tmp_path / "outer.flags"
    outer.write_text(f"--count=2\n--flagfile={bad}\n")
    assert _error(f"--flagfile={outer}") == (2, line + "\n", False)


def test_a_missing_flagfile_or_a_directory_is_named_in_one_line(tmp_path):
    missing = tmp_path / "missing.flags"
    assert _error(f"--flagfile={missing}") == (
        2,
        f"--flagfile={missing}: No such file or directory\n",
        False,
    )
    assert _error(f"--flagfile={tmp_path}") == (
        2,
        f"--flagfile={tmp_path}: Is a directory\n",
        False,
    )


def test_a_bad_flag_value_or_an_unknown_flag_is_one_line_without_help():
    assert _error("--count=0") == (2, "flag --count=0: 0 is not a positive integer\n", False)
    assert _error("--cuont=2") == (
        2,
        "Unknown command line flag 'cuont'. Did you mean: count ?\n",
        False,
    )


@pytest.mark.parametrize(
    "fail, status, line",
    [
        ("usage", 2, "--count: not a count of anything"),
        ("argument", 2, "--split=val: the dataset has only ['test', 'train']"),
        ("held", 1, "workdir runs/x is in use by another training run"),
        ("disk_full", 1, "disk full: no space left to write in runs/x"),
        (
            "wrapped_disk_full",
            1,
            "disk full: [Errno 28] No space left on device: 'runs/x/m.json'",
        ),
        ("no_intact_checkpoint", 1, "no checkpoint in runs/x is intact"),
        ("nan", 1, "loss is nan at step 7; stopping"),
    ],
)
def test_an_error_that_says_what_went_wrong_ends_the_launcher_in_one_line(fail, status, line):
    assert _error(f"--fail={fail}") == (status, line + "\n", False)


def test_a_bug_keeps_its_traceback():
    result = _launch("--fail=bug")
    assert result.returncode == 1
    assert "Traceback (most recent call last)" in result.stderr
    assert result.stderr.rstrip().endswith("KeyError: 'a bug'")


def test_the_dataset_launchers_say_a_users_mistake_in_one_line(tmp_path):
    """data.build and data.demon.convert end as every launcher does (the refusals
    themselves: tests/data/test_prepare.py)."""
    data_dir = tmp_path / "datasets"
    missing = tmp_path / "no_such_folder"
    cases = [
        (
            ["data.build", "--dataset=gld_scenes/smal", f"--data_dir={data_dir}"],
            "--dataset=gld_scenes/smal: unknown config 'smal' of dataset 'gld_scenes'; valid: ",
        ),
        (
            ["data.build", "--dataset=demon/sun3d", f"--manual_dir={missing}"],
            f"--manual_dir={missing}: no such directory (",
        ),
        (["data.demon.convert", "--images=x"], "flag --poses=None: Flag --poses must have"),
    ]
    for (module, *args), start in cases:
        result = launch(module, *args, timeout=120)
        lines = result.stderr.splitlines()
        assert (result.returncode, len(lines)) == (2, 1), (args, result.stderr)
        assert lines[0].startswith(start), (args, lines[0])
    assert not data_dir.exists()  # nothing written
