"""How many sweeps the team's Jacobi eigensolver (odometry/solve/ops.py) takes on a 6x6, run as
plain Python on one lane: the least cap on its sweeps that gives the uncapped eigenpairs bit for
bit. Counted, so no GPU is needed (solve_kernel_time.py, warm_start_sweeps.py)."""

from __future__ import annotations

from functools import cache
from typing import Any

import numpy as np

from kintinuous_fast.odometry.solve.lane_ops import MAX_SWEEPS
from kintinuous_fast.odometry.solve.ops import SCRATCH_MATRICES, build_ops


@cache
def _capped(cap: int) -> Any:
    return build_ops(lambda function: function, max_sweeps=cap)


def _eigen(a: np.ndarray, basis: np.ndarray, cap: int) -> tuple[np.ndarray, np.ndarray]:
    values, vectors = np.empty(6), np.empty((6, 6))
    scratch = np.zeros((SCRATCH_MATRICES, 6, 6))
    _capped(cap).symmetric_eigen_from(a, basis, values, vectors, scratch, 0, 1)
    return values, vectors


def sweeps_taken(a: np.ndarray, basis: np.ndarray | None = None) -> tuple[int, np.ndarray]:
    """(sweeps, eigenvectors as columns) of the symmetric `a` started from `basis` (None: the
    identity)."""
    basis = np.eye(6) if basis is None else basis
    values, vectors = _eigen(a, basis, MAX_SWEEPS)
    for cap in range(MAX_SWEEPS):
        capped = _eigen(a, basis, cap)
        if np.array_equal(capped[0], values) and np.array_equal(capped[1], vectors):
            return cap, vectors
    return MAX_SWEEPS, vectors
