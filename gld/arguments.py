"""The two errors a launcher says in one line (`data.command_line`), with no traceback:

- `ArgumentError`: an argument a caller gave is wrong. A library function that checks
  what it was given before it reads or writes anything raises it, its message naming the
  argument (as the launcher's flag, `--workdir: ...`); a usage error (exit status 2).
  `MissingInputError` is one: a named file or folder that is not there.
- `RunStoppedError`: a run cannot go on (its workdir is held by another run, the disk is
  full, no checkpoint is intact, the loss became NaN); exit status 1.

Any other error keeps its traceback: it is a bug to see.
"""

from __future__ import annotations


class ArgumentError(ValueError):
    """An argument is wrong; the message says which and why, in one line."""


class MissingInputError(ArgumentError, FileNotFoundError):
    """A file or folder the caller named is not there, or holds nothing to read (a
    workdir without a checkpoint); the message names it. Still a FileNotFoundError."""


class RunStoppedError(RuntimeError):
    """A run cannot go on; the message says why, in one line."""
