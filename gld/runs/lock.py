"""A run's lock: one training process per workdir.

    with WorkdirLock(workdir): ...         # <workdir>/train.lock

One training process per workdir. `WorkdirLock` takes an exclusive `flock` on
`train.lock` and writes its owner (pid, host, start time, command line) into it; a second
launch is refused with that owner's name. The kernel drops the lock when its process
dies, so a killed run never leaves it stuck. In a multi-process run only process 0 takes
it; readers (evaluation, inspection) need none.
"""

from __future__ import annotations

import contextlib
import datetime
import fcntl
import json
import os
import shlex
import socket
import sys
from collections.abc import Iterator
from pathlib import Path

import jax

from gld.arguments import RunStoppedError

LOCK_FILE = "train.lock"


class WorkdirLockedError(RunStoppedError):
    """Another training process holds the workdir."""


class WorkdirLock:
    """An exclusive lock on `<workdir>/train.lock`, naming its owner in the file.

    Use as a context manager, or `acquire()` / `release()`. The lock belongs to the open
    file, so the kernel releases it when the owning process exits, however it exits.
    """

    def __init__(self, workdir: str | Path):
        self.path = Path(workdir) / LOCK_FILE
        self._fd: int | None = None
        self._created_workdir = False

    def acquire(self) -> None:
        """Takes the lock, creating the workdir if needed.

        Raises:
          WorkdirLockedError: another process holds it (its pid, host, start time and
            command line are in the message).
        """
        self._created_workdir = not self.path.parent.exists()
        self.path.parent.mkdir(parents=True, exist_ok=True)
        while True:
            fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                owner = _describe_owner(os.pread(fd, 1 << 16, 0))
                os.close(fd)
                raise WorkdirLockedError(
                    f"workdir {self.path.parent} is in use by another training run ({owner}); "
                    f"wait for it to end or use another --workdir (lock file {self.path})"
                ) from None
            if _is_the_file_at(fd, self.path):
                break
            # Its holder removed the file (a first launch that wrote nothing) while this
            # process waited to lock it: lock the file now at the path.
            os.close(fd)
            self.path.parent.mkdir(parents=True, exist_ok=True)
        owner = {
            "pid": os.getpid(),
            "host": socket.gethostname(),
            "started": datetime.datetime.now().astimezone().isoformat(timespec="seconds"),
            "command": _command_line(),
        }
        os.ftruncate(fd, 0)
        os.pwrite(fd, (json.dumps(owner) + "\n").encode(), 0)
        self._fd = fd

    def release(self) -> None:
        """Releases the lock (a no-op when not held); the file stays, emptied, unless
        this lock created the workdir and nothing else was written in it: then the file
        and the workdir are removed."""
        if self._fd is None:
            return
        # Emptied first, so the file never names a process that no longer holds it.
        os.ftruncate(self._fd, 0)
        workdir = self.path.parent
        if self._created_workdir and [p.name for p in workdir.iterdir()] == [LOCK_FILE]:
            # A first launch that wrote nothing leaves nothing: not even its lock.
            self.path.unlink()
            with contextlib.suppress(OSError):
                workdir.rmdir()
        fcntl.flock(self._fd, fcntl.LOCK_UN)
        os.close(self._fd)
        self._fd = None

    def __enter__(self) -> WorkdirLock:
        self.acquire()
        return self

    def __exit__(self, *exc_info) -> None:
        self.release()


def _is_the_file_at(fd: int, path: Path) -> bool:
    """Whether the open file `fd` is the file at `path` (not one removed since)."""
    try:
        return os.path.samestat(os.fstat(fd), os.stat(path))
    except FileNotFoundError:
        return False


def _command_line() -> str:
    """This process's command line as typed (`python -m ...`), where /proc has it."""
    try:
        arguments = Path("/proc/self/cmdline").read_bytes().rstrip(b"\0").split(b"\0")
        return shlex.join(argument.decode(errors="replace") for argument in arguments)
    except OSError:
        return shlex.join([sys.executable, *sys.argv])


def _describe_owner(content: bytes) -> str:
    try:
        owner = json.loads(content)
        return (
            f"pid {owner['pid']} on host {owner['host']}, started {owner['started']}, "
            f"command: {owner['command']}"
        )
    except (ValueError, KeyError, TypeError):
        return "its owner has not recorded itself yet"


@contextlib.contextmanager
def training_lock(workdir: str | Path) -> Iterator[None]:
    """`WorkdirLock` on process 0; other processes of a multi-process run share the
    workdir under process 0's lock."""
    if jax.process_index() != 0:
        yield
        return
    with WorkdirLock(workdir):
        yield
