"""Files written so that a reader, or a killed writer, sees the old file or the new one.

    write_atomically(path, text)                       # str or bytes
    write_atomically(path, lambda tmp: save(tmp))      # a writer that needs a path

Every file the project writes whole (configs, checksums, reports, exported models) goes
through `write_atomically`: a temporary file in the same folder, synced, then
`os.replace`.
"""

from __future__ import annotations

import os
import tempfile
from collections.abc import Callable
from pathlib import Path


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
