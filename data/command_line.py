"""How a command-line program of gld starts and ends: every launcher, `data`'s
(`data.build`, `data.demon.convert`) and `experiments`' (through `experiments.common`),
the benchmarks included. It lives on the data floor, the lowest that reads flags (`gld`
reads none), so that both can import it.

`run(main)` runs `main(argv)` under absl with the flags parsed by `parse_flags`, in a
process that keeps the memory it frees for reuse (`gld.host_memory`). A user's
mistake ends it with one line on stderr naming the flag or the file and what is wrong,
no traceback and no help text, before anything is written:
- exit status 2: a bad command line (a bad value, an unknown flag, a flagfile that is
  missing, a directory or not UTF-8 text), a usage error (`app.UsageError`) and an
  argument that does not fit the data or the workdir (`gld.arguments.ArgumentError`);
- exit status 1: a condition that stops a run (a workdir held by another run, a full
  disk however the writer wrapped it, a workdir without an intact checkpoint, a loss that
  became NaN: `gld.arguments.RunStoppedError`).
Any other error is a bug and keeps its traceback.
"""

from __future__ import annotations

import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any, NoReturn

from absl import flags

from gld import host_memory
from gld.arguments import ArgumentError, RunStoppedError
from gld.files import no_space_error

USAGE_STATUS = 2  # the command line, or an argument, is wrong
STOPPED_STATUS = 1  # the run could not go on (held, disk full, damaged, NaN)

FLAGS = flags.FLAGS


def run(main: Callable[[list[str]], Any]) -> None:
    """Runs a launcher's `main(argv)` under absl (`app.run`), its flags parsed by
    `parse_flags`; an error that says what went wrong ends it in one line (above)."""
    from absl import app

    host_memory.keep_freed_memory()

    def main_in_one_line(argv: list[str]) -> Any:
        try:
            return main(argv)
        except Exception as error:
            said = _line_of(error)
            if said is None:
                raise
            _stop(*said)

    app.run(main_in_one_line, flags_parser=parse_flags)


def parse_flags(argv: list[str]) -> list[str]:
    """Parses the command line into FLAGS (`app.run`'s flags_parser) and returns what is
    left of it. A bad command line ends the program with one line naming the flag or the
    flagfile and what is wrong with it, before anything runs."""
    try:
        return FLAGS(argv)
    except flags.CantOpenFlagFileError as error:
        reason = error.__context__  # the OSError absl's message was made from
        if isinstance(reason, OSError) and reason.filename:
            _stop(f"--flagfile={reason.filename}: {reason.strerror}", USAGE_STATUS)
        _stop(one_line(str(error).removeprefix("ERROR:: ")), USAGE_STATUS)
    except flags.Error as error:
        _stop(one_line(str(error)), USAGE_STATUS)
    except UnicodeDecodeError as error:
        _stop(_undecodable_flagfile(error), USAGE_STATUS)


def _undecodable_flagfile(error: UnicodeDecodeError) -> str:
    """The line for a flagfile absl could not decode: the file (absl's reader, nested
    flagfiles included, names it `filename`), the line and the byte."""
    path, frame = None, error.__traceback__
    while frame is not None:
        if frame.tb_frame.f_code.co_name == "_get_flag_file_lines":
            path = frame.tb_frame.f_locals.get("filename", path)
        frame = frame.tb_next
    encoding = error.encoding.upper()
    try:
        data = Path(path).read_bytes()
        data.decode(error.encoding)
    except UnicodeDecodeError as found:
        line = data.count(b"\n", 0, found.start) + 1
        return (
            f"--flagfile={path}: line {line} is not {encoding} text (byte "
            f"0x{data[found.start]:02x}); save the file as {encoding}"
        )
    except (OSError, TypeError):
        pass
    return f"--flagfile={path or '?'}: not {encoding} text ({error.reason}); save it as {encoding}"


def _line_of(error: Exception) -> tuple[str, int] | None:
    """The one line that says what `error` is and the exit status, when it says what
    went wrong (None for the others: bugs, whose traceback is wanted)."""
    from absl import app

    if isinstance(error, app.UsageError | ArgumentError):
        return one_line(str(error)), USAGE_STATUS
    if isinstance(error, RunStoppedError):
        return one_line(str(error)), STOPPED_STATUS
    no_space = no_space_error(error)
    if no_space is not None:
        return one_line(f"disk full: {no_space}"), STOPPED_STATUS
    return None


def one_line(text: str) -> str:
    """`text` with its whitespace runs, newlines included, made single spaces."""
    return " ".join(text.split())


def _stop(line: str, status: int) -> NoReturn:
    print(line, file=sys.stderr, flush=True)
    sys.exit(status)
