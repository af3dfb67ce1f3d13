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
# never over a value that XLA_FLAGS already gives.
CPU_FUSION_FLAG = "--xla_cpu_experimental_ynn_fusion_type=-reduce"


def _jaxlib_version() -> tuple[int, ...]:
    try:
        version = importlib.metadata.version("jaxlib")
    except importlib.metadata.PackageNotFoundError:
        return ()
    return tuple(int(part) for part in version.split(".")[:2] if part.isdigit())


if _jaxlib_version() >= (0, 10) and "ynn_fusion_type" not in os.environ.get("XLA_FLAGS", ""):
    os.environ["XLA_FLAGS"] = f"{os.environ.get('XLA_FLAGS', '')} {CPU_FUSION_FLAG}".strip()
