# ruff: noqa: ANN001, ANN202  (numba loops: argument types come from the call)
"""kintinuous_ref.odometry.solve on the CPU: `accumulate` summed in fixed chunks on all threads
(odometry/sums/cpu.py), the compiled Gauss-Newton step (solve/__init__.py), the reference's
own LinearSystem and plausibility test."""

from __future__ import annotations

import numpy as np

from kintinuous_fast.odometry.sums import sum_partials
from kintinuous_fast.odometry.sums.cpu import LOOP, add_column, partials, run
from kintinuous_fast.targets.cpu import claimed_items
from kintinuous_ref.odometry.solve import LinearSystem
from kintinuous_ref.odometry.solve import implausible_motion as implausible_motion

from . import TARGET_ALL
from . import apply_increment as apply_increment
from . import refine as refine
from . import solve as solve

__all__ = TARGET_ALL


@LOOP
def _accumulate_loop(claims, parts, jacobian, residuals, weights, weighted, out):
    n = residuals.shape[0]
    chunks = out.shape[0]
    for c in claimed_items(claims, chunks, parts):
        acc = out[c]
        for k in range(c * n // chunks, (c + 1) * n // chunks):
            w = weights[k] if weighted else 1.0
            add_column(acc, jacobian, k, residuals[k], w)


def accumulate(
    jacobian: np.ndarray, residuals: np.ndarray, weights: np.ndarray | None = None
) -> LinearSystem:
    """Normal equations of the (6, N) Jacobian and (N,) residuals in float64, chunked sums."""
    residuals = np.ascontiguousarray(residuals, dtype=np.float64)
    out = partials(len(residuals))
    weighted = weights is not None
    run(
        _accumulate_loop,
        len(residuals),
        np.ascontiguousarray(jacobian, dtype=np.float64),
        residuals,
        np.ascontiguousarray(weights, dtype=np.float64) if weighted else residuals,
        weighted,
        out,
    )
    return sum_partials(out)[0]
