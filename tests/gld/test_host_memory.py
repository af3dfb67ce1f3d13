import json
import os
import platform

import pytest
from conftest import _interpreter

from gld import host_memory

pytestmark = pytest.mark.skipif(platform.libc_ver()[0] != "glibc", reason="glibc's malloc")

# Allocates, touches, frees and again allocates and touches 64 MB (above the 32 MB that
# glibc's mmap threshold rises to) and prints the page faults of the second allocation:
# after keep_freed_memory() ("keep"), as a launcher's main under data.command_line.run
# ("launcher"), or as it is ("default").
FAULTS_SCRIPT = """
import ctypes, json, resource, sys
from gld import host_memory

def measure(argv=None, applied=None):
    libc = ctypes.CDLL(None)
    libc.malloc.restype = ctypes.c_void_p
    libc.free.argtypes = [ctypes.c_void_p]
    size = 64 << 20
    buffer = libc.malloc(size)
    ctypes.memset(buffer, 1, size)
    libc.free(buffer)
    before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    buffer = libc.malloc(size)
    ctypes.memset(buffer, 1, size)
    faults = resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before
    print(json.dumps({"applied": applied, "faults": faults}))

mode = sys.argv.pop(1)
if mode == "launcher":
    from data import command_line
    command_line.run(measure)
else:
    measure(applied=host_memory.keep_freed_memory() if mode == "keep" else None)
"""


def _faults(mode: str, **environment: str) -> dict:
    # The child's malloc options are only these: any in this environment are removed.
    removed = {
        name: None for name in os.environ if name.startswith("MALLOC_") or name == "GLIBC_TUNABLES"
    }
    result = _interpreter(["-c", FAULTS_SCRIPT, mode], timeout=120, env={**removed, **environment})
    assert result.returncode == 0, result.stderr[-2000:]
    return json.loads(result.stdout.strip().splitlines()[-1])


def test_a_freed_large_buffer_is_reused_without_faulting_its_pages_again():
    pages = (64 << 20) // os.sysconf("SC_PAGE_SIZE")
    # By default glibc maps the buffer afresh: every page faults again.
    assert _faults("default")["faults"] >= pages // 2
    kept = _faults("keep")
    assert kept["applied"] is True
    assert kept["faults"] < pages // 100
    # Every launcher's main runs with it.
    assert _faults("launcher")["faults"] < pages // 100
    # The same setting given to a child process through its environment.
    assert _faults("default", **host_memory.ENVIRONMENT)["faults"] < pages // 100


def test_malloc_options_the_environment_sets_are_left_alone():
    assert host_memory.set_by_environment({"MALLOC_ARENA_MAX": "2"}) is False
    assert host_memory.set_by_environment({"MALLOC_MMAP_THRESHOLD_": "1"}) is True
    assert host_memory.set_by_environment({"GLIBC_TUNABLES": "glibc.malloc.hugetlb=1"}) is True
    assert host_memory.set_by_environment({"GLIBC_TUNABLES": "glibc.rtld.nns=2"}) is False
    # The user's own threshold: nothing applied, and the default's faults stay.
    kept = _faults("keep", MALLOC_MMAP_THRESHOLD_="131072")
    assert kept["applied"] is False
    assert kept["faults"] >= (64 << 20) // os.sysconf("SC_PAGE_SIZE") // 2
