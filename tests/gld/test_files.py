"""A full disk is told apart from other failures through the wrappers around it
(`gld.files.no_space_error`); a folder that cannot be written in is found by a probe
(`gld.files.write_problem`)."""

import errno
import os
from pathlib import Path

import pytest

from gld import files


def _raised(make_error):
    try:
        make_error()
    except Exception as error:
        return error
    raise AssertionError("nothing raised")


def test_a_full_disk_is_found_however_it_is_wrapped():
    full = OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), "runs/x/metrics.jsonl")

    def wrapped():
        try:
            raise full
        except OSError as error:
            raise RuntimeError("the save thread failed") from error

    def hidden():  # `from None` keeps the context, unshown
        try:
            raise full
        except OSError:
            raise ValueError("could not save") from None

    assert files.no_space_error(full) is full
    assert files.no_space_error(_raised(wrapped)) is full
    assert files.no_space_error(_raised(hidden)) is full
    assert files.no_space_error(ExceptionGroup("saves", [ValueError("a"), full])) is full
    quota = OSError(errno.EDQUOT, os.strerror(errno.EDQUOT))
    assert files.no_space_error(quota) is quota
    # tensorstore's report of it, as orbax raises it
    store = ValueError(
        "RESOURCE_EXHAUSTED: Failed to write 295463 bytes to file 5: No space "
        "left on device [os_error_code='28']"
    )
    assert files.no_space_error(store) is store
    stopped = files.DiskFullError("disk full: no space left in runs/x")
    assert files.no_space_error(stopped) is stopped


def test_other_failures_are_not_a_full_disk():
    for error in (
        OSError(errno.EACCES, os.strerror(errno.EACCES), "runs/x"),
        FileNotFoundError(errno.ENOENT, os.strerror(errno.ENOENT), "runs/x"),
        ValueError("RESOURCE_EXHAUSTED: out of memory"),
        KeyError("space"),
    ):
        assert files.no_space_error(error) is None, error


def test_a_writable_folder_is_probed_and_nothing_is_left(tmp_path):
    assert files.write_problem(tmp_path) is None
    assert files.write_problem(tmp_path / "new" / "eval") is None
    assert list(tmp_path.iterdir()) == []  # the probe removed, the missing folders not made
    (tmp_path / "plain").write_text("x")
    assert (
        files.write_problem(tmp_path / "plain" / "eval") == f"{tmp_path / 'plain'} is not a folder"
    )


@pytest.mark.skipif(not Path("/proc/self").is_dir(), reason="needs /proc")
def test_a_folder_nobody_can_write_in_is_named():
    # Permission bits do not stop root; /proc stops everyone.
    assert files.write_problem("/proc/self/run/eval").startswith("cannot write in /proc/self (")
