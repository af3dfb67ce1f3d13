"""The error of an argument a caller gave: a library function that checks what it was
given before it reads or writes anything raises `ArgumentError`, whose message names the
argument (as the launcher's flag, `--workdir: ...`); a launcher shows it as a usage error,
and any other error keeps its traceback."""

from __future__ import annotations


class ArgumentError(ValueError):
    """An argument is wrong; the message says which and why, in one line."""
