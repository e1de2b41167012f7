"""Small dense matrices in compiled host code: the products, transposes and skew matrices of
the Gauss-Newton step (solve/__init__.py) and of the joint system (odometry/combined.py).

Plain loops: numba compiles them in a fraction of the time of its array expressions, and they
equal BLAS's products to rounding (tests/test_fast_solve.py).
"""

from __future__ import annotations

import numba
import numpy as np

__all__ = ["column", "product", "skew", "transposed"]

_jit = numba.njit(cache=True)


@_jit
def product(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """a @ b of small matrices."""
    out = np.zeros((a.shape[0], b.shape[1]))
    for i in range(a.shape[0]):
        for k in range(a.shape[1]):
            for j in range(b.shape[1]):
                out[i, j] += a[i, k] * b[k, j]
    return out


@_jit
def transposed(a: np.ndarray) -> np.ndarray:
    """a.T as a new C-contiguous matrix."""
    out = np.empty((a.shape[1], a.shape[0]))
    for i in range(a.shape[0]):
        for j in range(a.shape[1]):
            out[j, i] = a[i, j]
    return out


@_jit
def column(v: np.ndarray) -> np.ndarray:
    """v as a (n, 1) matrix."""
    out = np.empty((len(v), 1))
    for i in range(len(v)):
        out[i, 0] = v[i]
    return out


@_jit
def skew(x: float, y: float, z: float) -> np.ndarray:
    """kintinuous_ref.se3.skew of (x, y, z)."""
    m = np.zeros((3, 3))
    m[0, 1], m[0, 2] = -z, y
    m[1, 0], m[1, 2] = z, -x
    m[2, 0], m[2, 1] = -y, x
    return m
