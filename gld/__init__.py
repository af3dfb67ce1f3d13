"""gld: learning dense depth from two views and optical flow with very sparse supervision."""

import importlib.metadata
import os

__version__ = "0.1.0"

# XLA's CPU backend hands reductions to its YNNPACK library by default (jaxlib 0.10).
# The model's reductions are small (the pose refinement's sums over 3-vectors, the
# encoder's pooling), and XLA's own loops run them much faster: the main job's train step
# on the 2-core AMD EPYC took 470 ms with them in YNNPACK and 385 ms without, the pose
# refinement 95 ms and 30 ms of it. Dots and convolutions stay in YNNPACK. The option is
# read when JAX starts its backend, so it is set on import, before any computation, and
# never over a value that XLA_FLAGS already gives. XLA aborts on a flag or value it does
# not know, so it is set only for the jaxlib versions it was measured with (0.10).
CPU_FUSION_FLAG = "--xla_cpu_experimental_ynn_fusion_type=-reduce"
CPU_FUSION_JAXLIB = ((0, 10),)


def _jaxlib_version() -> tuple[int, ...]:
    try:
        version = importlib.metadata.version("jaxlib")
    except importlib.metadata.PackageNotFoundError:
        return ()
    return tuple(int(part) for part in version.split(".")[:2] if part.isdigit())


def sets_cpu_fusion_flag() -> bool:
    """Whether importing gld adds `CPU_FUSION_FLAG` to XLA_FLAGS here."""
    return _jaxlib_version() in CPU_FUSION_JAXLIB


if sets_cpu_fusion_flag() and "ynn_fusion_type" not in os.environ.get("XLA_FLAGS", ""):
    os.environ["XLA_FLAGS"] = f"{os.environ.get('XLA_FLAGS', '')} {CPU_FUSION_FLAG}".strip()
