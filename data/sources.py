"""What a build was made from: fingerprints of its input files, and how two sets differ.

A built dataset records the fingerprint of every manual-directory file it read
(`builder.info.metadata["sources"]`, `{split: {file name: fingerprint}}`), so that
`data.prepare` can tell whether a later `manual_dir` still holds the same files.

A fingerprint is the file's size and the SHA-256 of its first and last MiB (the
whole file when it is at most 2 MiB), with its resolved path and modification time
kept for the messages. Comparing one costs two 1 MiB reads per file whatever its
size, so every launcher run can afford it, where a full hash of DeMoN's training
files (tens of GB) could not be recomputed at each start. Content decides: a file
whose path or modification time changed but whose size and both ends did not (the
folder was moved or copied) is the same file. Not noticed: an edit in place that
keeps the size and both ends of the file; rebuild after such an edit.
"""

from __future__ import annotations

import hashlib
import os
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

# Bytes hashed at each end of a file.
END_BYTES = 1 << 20


def fingerprint(path: str | os.PathLike) -> dict[str, Any]:
    """{"path", "size", "mtime_ns", "sha256_ends"} of one file (see the module docstring)."""
    path = Path(path).expanduser().resolve()
    stat = path.stat()
    digest = hashlib.sha256()
    with open(path, "rb") as stream:
        if stat.st_size <= 2 * END_BYTES:
            digest.update(stream.read())
        else:
            digest.update(stream.read(END_BYTES))
            stream.seek(-END_BYTES, os.SEEK_END)
            digest.update(stream.read(END_BYTES))
    return {
        "path": str(path),
        "size": stat.st_size,
        "mtime_ns": stat.st_mtime_ns,
        "sha256_ends": digest.hexdigest(),
    }


def fingerprints(split_files: Mapping[str, Iterable[str | os.PathLike]]) -> dict[str, Any]:
    """{split: [paths]} -> {split: {file name: fingerprint}}, JSON-serialisable."""
    return {
        split: {Path(path).name: fingerprint(path) for path in paths}
        for split, paths in split_files.items()
    }


def _same_content(recorded: Mapping[str, Any], current: Mapping[str, Any]) -> bool:
    return (
        recorded.get("size") == current["size"]
        and recorded.get("sha256_ends") == current["sha256_ends"]
    )


def changes(recorded: Mapping[str, Any], current: Mapping[str, Any]) -> list[str]:
    """How the files of `current` differ from those a build `recorded`, one line each.

    Args:
      recorded, current: `fingerprints(...)` results, {split: {file name: fingerprint}}.

    Returns:
      "<split> split: <file> added (<path>)", "... removed (was <path>)" or "... changed
      (<what>: <old> -> <new>; was <old path>, now <new path>)" per differing file; empty
      when every split holds files of the same content (wherever they now lie).
    """
    lines = []
    for split in sorted(set(recorded) | set(current)):
        before, after = recorded.get(split, {}), current.get(split, {})
        for name in sorted(set(before) | set(after)):
            if name not in before:
                lines.append(f"{split} split: {name} added ({after[name]['path']})")
            elif name not in after:
                lines.append(f"{split} split: {name} removed (was {before[name].get('path')})")
            elif not _same_content(before[name], after[name]):
                old, new = before[name], after[name]
                if old.get("size") != new["size"]:
                    what = f"size {old.get('size')} -> {new['size']} bytes"
                else:
                    what = "same size, other content"
                lines.append(
                    f"{split} split: {name} changed ({what}; was {old.get('path')}, "
                    f"now {new['path']})"
                )
    return lines
