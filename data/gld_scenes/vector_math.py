"""The ray caster's reproducible arithmetic: BLAS-free small products, safe reciprocals.

A render must be bit-identical whatever the thread count and array size (an example is
a pure function of its seed), so the renderer's small matrix products avoid BLAS; and a
ray parallel to a plane must meet it at a finite distance, so divisions by a ray's
components avoid dividing by zero.
"""

from __future__ import annotations

import numpy as np


def transform(vectors: np.ndarray, matrix: np.ndarray) -> np.ndarray:
    """`vectors @ matrix` for [N, 3] @ [3, K] without BLAS.

    Elementwise products give bit-identical results whatever the thread count and
    array size (BLAS kernels may not), which keeps renders reproducible.
    """
    matrix = np.asarray(matrix, vectors.dtype)
    if matrix.ndim == 1:
        return vectors[:, 0] * matrix[0] + vectors[:, 1] * matrix[1] + vectors[:, 2] * matrix[2]
    return vectors[:, :1] * matrix[0] + vectors[:, 1:2] * matrix[1] + vectors[:, 2:3] * matrix[2]


def safe_reciprocal(values: np.ndarray) -> np.ndarray:
    """1 / values, with values nearer 0 than 1e-12 replaced by +/-1e-12 (0 by +1e-12):
    finite for every finite input."""
    tiny = np.float32(1e-12)
    return 1.0 / np.where(np.abs(values) < tiny, np.where(values < 0, -tiny, tiny), values)
