"""Tests of data/sources.py: file fingerprints and the differences between two sets."""

from __future__ import annotations

import os
import shutil

import numpy as np

from data import sources

MIB = sources.END_BYTES


def _write(path, size, seed=0):
    path.write_bytes(np.random.default_rng(seed).integers(0, 256, size, np.uint8).tobytes())
    return path


def _patched(path, offset, value=b"\x00\x01"):
    """A copy of `path` next to it with `value` written at `offset` (same size)."""
    copy = path.with_name(f"{path.stem}_{offset}{path.suffix}")
    shutil.copyfile(path, copy)
    with open(copy, "r+b") as stream:
        stream.seek(offset)
        stream.write(value)
    return copy


def test_fingerprint_follows_size_and_both_ends(tmp_path):
    original = _write(tmp_path / "big.h5", 3 * MIB)
    base = sources.fingerprint(original)
    assert base["size"] == 3 * MIB and base["path"] == str(original.resolve())
    for offset in (10, 3 * MIB - 10):  # first and last MiB
        assert sources.fingerprint(_patched(original, offset))["sha256_ends"] != base["sha256_ends"]
    # A small file is hashed whole, so any byte counts.
    small = _write(tmp_path / "small.h5", MIB + 100, seed=1)
    middle = _patched(small, MIB // 2 + 50)
    assert sources.fingerprint(middle)["sha256_ends"] != sources.fingerprint(small)["sha256_ends"]


def test_moved_copy_is_the_same_file_and_changes_are_named(tmp_path):
    (tmp_path / "a").mkdir()
    _write(tmp_path / "a" / "custom_train.h5", 5000)
    _write(tmp_path / "a" / "custom_test.h5", 3000, seed=2)
    recorded = sources.fingerprints(
        {"train": [tmp_path / "a" / "custom_train.h5"], "test": [tmp_path / "a" / "custom_test.h5"]}
    )
    shutil.copytree(tmp_path / "a", tmp_path / "b")  # new paths and modification times
    os.utime(tmp_path / "b" / "custom_train.h5", ns=(0, 0))
    moved = sources.fingerprints(
        {"train": [tmp_path / "b" / "custom_train.h5"], "test": [tmp_path / "b" / "custom_test.h5"]}
    )
    assert sources.changes(recorded, moved) == []

    _write(tmp_path / "b" / "custom_train.h5", 5001, seed=3)
    _write(tmp_path / "b" / "custom_train_lab.h5", 10, seed=4)
    current = sources.fingerprints(
        {"train": [tmp_path / "b" / "custom_train.h5", tmp_path / "b" / "custom_train_lab.h5"]}
    )
    a, b = tmp_path.resolve() / "a", tmp_path.resolve() / "b"
    assert sources.changes(recorded, current) == [
        f"test split: custom_test.h5 removed (was {a / 'custom_test.h5'})",
        f"train split: custom_train.h5 changed (size 5000 -> 5001 bytes; was "
        f"{a / 'custom_train.h5'}, now {b / 'custom_train.h5'})",
        f"train split: custom_train_lab.h5 added ({b / 'custom_train_lab.h5'})",
    ]
