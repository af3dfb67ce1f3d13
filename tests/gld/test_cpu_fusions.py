"""Importing gld keeps XLA's CPU reductions out of YNNPACK (gld/__init__.py), unless
XLA_FLAGS says otherwise."""

import os
import subprocess
import sys

import pytest

import gld

# A fresh interpreter: imports gld, compiles a small reduction for the CPU and prints
# XLA_FLAGS, then whether the compiled program hands any fusion to YNNPACK.
SCRIPT = """
import gld, os
import jax, jax.numpy as jnp
x = jnp.ones((40, 192, 3))
text = jax.jit(lambda a, b: jnp.sum(a * b, axis=-1)).lower(x, x).compile().as_text()
print(os.environ.get("XLA_FLAGS", ""))
print("__ynn_fusion" in text)
"""


def _run(xla_flags: str | None) -> tuple[str, bool]:
    env = {k: v for k, v in os.environ.items() if k != "XLA_FLAGS"}
    env["JAX_PLATFORMS"] = "cpu"
    if xla_flags is not None:
        env["XLA_FLAGS"] = xla_flags
    completed = subprocess.run(
        [sys.executable, "-c", SCRIPT], capture_output=True, text=True, env=env, timeout=300
    )
    assert completed.returncode == 0, completed.stderr[-2000:]
    flags, in_library = completed.stdout.strip().splitlines()[-2:]
    return flags, in_library == "True"


@pytest.mark.skipif(not gld.sets_cpu_fusion_flag(), reason="the option is set for jaxlib 0.10")
def test_the_cpu_reductions_stay_out_of_the_library_unless_xla_flags_says_otherwise():
    flags, in_library = _run(None)
    assert flags == gld.CPU_FUSION_FLAG
    assert not in_library
    # Another flag is kept, and the option is added beside it.
    flags, in_library = _run("--xla_cpu_enable_fast_math=false")
    assert flags == f"--xla_cpu_enable_fast_math=false {gld.CPU_FUSION_FLAG}"
    assert not in_library
    # The user's own choice of library fusions is left alone: here, reductions in it.
    own = "--xla_cpu_experimental_ynn_fusion_type=reduce"
    flags, in_library = _run(own)
    assert flags == own
    assert in_library
