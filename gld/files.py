"""Files written so that a reader, or a killed writer, sees the old file or the new one.

    write_atomically(path, text)                       # str or bytes
    write_atomically(path, lambda tmp: save(tmp))      # a writer that needs a path

Every file the project writes whole (configs, checksums, reports, exported models) goes
through `write_atomically`: a temporary file in the same folder, synced, then
`os.replace`.

A full disk (or quota) is told apart from other failures by `no_space_error`, through
the wrappers orbax puts around it; `DiskFullError` is what a writer that knows the
directory raises instead, in one line.
"""

from __future__ import annotations

import errno
import os
import tempfile
from collections.abc import Callable
from pathlib import Path

from gld.arguments import RunStoppedError


def write_atomically(path: str | Path, content: str | bytes | Callable[[Path], None]) -> None:
    """Writes `content` to `path` through a temporary file in the same folder (made if
    missing) and `os.replace`. `content` is text, bytes, or a function that writes the
    file at the path it is given."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    handle, temporary = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        if callable(content):
            os.close(handle)
            content(Path(temporary))
        else:
            with os.fdopen(handle, "wb" if isinstance(content, bytes) else "w") as stream:
                stream.write(content)
                stream.flush()
                os.fsync(stream.fileno())
        os.replace(temporary, path)
    except BaseException:
        Path(temporary).unlink(missing_ok=True)
        raise


# errno values that mean the file system has no room for the write: disk full, quota used.
NO_SPACE_ERRNOS = (errno.ENOSPC, errno.EDQUOT)


class DiskFullError(RunStoppedError):
    """A write failed for lack of space; the message names the directory and what was kept."""


def no_space_error(error: BaseException) -> BaseException | None:
    """The error that says the file system is full, `error` or one it wraps (its cause,
    context or group members), or None: an OSError with errno ENOSPC or EDQUOT, a
    `DiskFullError`, or the message of one as tensorstore gives it to orbax
    (`ValueError: RESOURCE_EXHAUSTED: ... No space left on device [os_error_code='28']`)."""
    markers = [os.strerror(code) for code in NO_SPACE_ERRNOS]
    markers += [f"[os_error_code='{code}']" for code in NO_SPACE_ERRNOS]
    pending, seen = [error], set()
    while pending:
        current = pending.pop()
        if current is None or id(current) in seen:
            continue
        seen.add(id(current))
        if isinstance(current, DiskFullError):
            return current
        if isinstance(current, OSError) and current.errno in NO_SPACE_ERRNOS:
            return current
        if any(marker in str(current) for marker in markers):
            return current
        pending += [current.__cause__, current.__context__]
        pending += list(getattr(current, "exceptions", ()))
    return None


def write_problem(folder: str | Path) -> str | None:
    """Why files cannot be written in `folder` (made if missing), or None.

    Tried with a probe file in `folder`, or in its nearest existing parent when it is
    missing, removed at once: permission bits do not stop root, and a read-only mount
    stops everyone. Nothing is left behind either way.
    """
    existing = Path(folder)
    while not existing.exists() and existing != existing.parent:
        existing = existing.parent
    if not existing.is_dir():
        return f"{existing} is not a folder"
    try:
        handle, probe = tempfile.mkstemp(dir=existing, prefix=".write-check-")
    except OSError as error:
        return f"cannot write in {existing} ({error.strerror or error})"
    os.close(handle)
    os.unlink(probe)
    return None
