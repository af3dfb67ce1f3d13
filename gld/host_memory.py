"""The process keeps the memory it frees for its next allocations (glibc's malloc).

    host_memory.keep_freed_memory()  # before the first step; True where it applied
    subprocess.run(command, env=host_memory.environment())  # the same for another program

XLA's CPU runtime allocates an executable's temporaries as one buffer each time the
executable runs, and glibc's malloc hands every allocation above 32 MB (the most its
mmap threshold can rise to) to the kernel with mmap, and gives it back when freed. So
each run faulted in and zeroed every page of a fresh buffer: the main job's train step
(42.7 MB of temporaries per device, two devices) took ~20,900 page faults a step, and
stood at 211 ms a step against 158 ms with them gone (WORKSPACE.md). Taking every
allocation from the heap (`M_MMAP_MAX` 0) and never trimming its top (`M_TRIM_THRESHOLD`
at its maximum) makes the next run reuse the pages of the last: the process's resident
memory stays at its peak instead of rising and falling with each step.

It applies to later allocations only, so it is called first: `data.command_line.run`
calls it before every launcher's main, the benchmark's workers at their start. `environment()` gives
another program the same setting as glibc reads it at a process's start (the
benchmark's PyTorch reference, which gains as much). Elsewhere than glibc,
or where the environment already sets malloc's options (`MALLOC_MMAP_MAX_`,
`MALLOC_TRIM_THRESHOLD_`, `MALLOC_MMAP_THRESHOLD_`, `MALLOC_TOP_PAD_` or a
`glibc.malloc` tunable in `GLIBC_TUNABLES`), it changes nothing.
"""

from __future__ import annotations

import ctypes
import os
import platform

# mallopt's parameters (malloc.h).
_M_TRIM_THRESHOLD = -1
_M_MMAP_MAX = -4
# The largest trim threshold mallopt takes (an int): the heap's top is never given back.
_NEVER_TRIM = 2**31 - 1
# The same options as environment variables, read by glibc when a process starts.
ENVIRONMENT = {"MALLOC_MMAP_MAX_": "0", "MALLOC_TRIM_THRESHOLD_": str(_NEVER_TRIM)}
_ENVIRONMENT_SETTINGS = (*ENVIRONMENT, "MALLOC_MMAP_THRESHOLD_", "MALLOC_TOP_PAD_")


def set_by_environment(environ: dict[str, str] | None = None) -> bool:
    """Whether the environment sets any of malloc's options itself."""
    environ = os.environ if environ is None else environ
    return any(name in environ for name in _ENVIRONMENT_SETTINGS) or (
        "glibc.malloc." in environ.get("GLIBC_TUNABLES", "")
    )


def _applies() -> bool:
    return platform.libc_ver()[0] == "glibc" and not set_by_environment()


def environment() -> dict[str, str]:
    """This process's environment, with `keep_freed_memory`'s setting for a child process
    where it applies here."""
    return {**os.environ, **(ENVIRONMENT if _applies() else {})}


def keep_freed_memory() -> bool:
    """Makes glibc's malloc serve every allocation from its heap and keep what is freed
    for reuse. Returns whether it applied (False off glibc or when the environment sets
    malloc's options)."""
    if not _applies():
        return False
    mallopt = ctypes.CDLL(None).mallopt
    mallopt.argtypes, mallopt.restype = (ctypes.c_int, ctypes.c_int), ctypes.c_int
    # mallopt returns 1 on success.
    return mallopt(_M_MMAP_MAX, 0) == 1 and mallopt(_M_TRIM_THRESHOLD, _NEVER_TRIM) == 1
