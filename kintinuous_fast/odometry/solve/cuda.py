# ruff: noqa: ANN001  (numba kernels: argument types come from the call)
"""kintinuous_ref.odometry.solve on CUDA: `accumulate` as per-thread sums and block trees in
shared memory (odometry/sums/cuda.py), the compiled Gauss-Newton step on the host
(solve/__init__.py, as the paper solves the 6x6 system on the CPU), the reference's own
LinearSystem and plausibility test."""

from __future__ import annotations

import numpy as np
from numba import cuda, float64

from kintinuous_fast.odometry.sums import NV, sum_partials
from kintinuous_fast.odometry.sums.cuda import (
    BLOCK,
    add_column,
    block_reduce,
    f64,
    reduction_blocks,
    zero,
)
from kintinuous_fast.targets import to_host
from kintinuous_fast.targets.cuda import kernel
from kintinuous_ref.odometry.solve import LinearSystem
from kintinuous_ref.odometry.solve import implausible_motion as implausible_motion

from . import TARGET_ALL
from . import apply_increment as apply_increment
from . import refine as refine
from . import solve as solve

__all__ = TARGET_ALL


@kernel
def _accumulate_kernel(jacobian, residuals, weights, weighted, out):
    shared = cuda.shared.array((NV, BLOCK), float64)
    acc = cuda.local.array(NV, float64)
    zero(acc)
    for k in range(cuda.grid(1), residuals.shape[0], cuda.gridsize(1)):
        w = weights[k] if weighted else 1.0
        add_column(acc, jacobian, k, residuals[k], w)
    block_reduce(acc, shared, out)


def accumulate(jacobian, residuals, weights=None) -> LinearSystem:  # noqa: ANN001
    """Normal equations of the (6, N) Jacobian and (N,) residuals: per-thread sums, block tree
    reductions in shared memory, block partials added on the host in float64."""
    n = residuals.shape[0]
    blocks = reduction_blocks(n)
    out = cuda.device_array((blocks, NV), dtype=np.float64)
    d_residuals = f64(residuals) if n else cuda.to_device(np.zeros(1))
    d_jacobian = f64(jacobian) if n else cuda.to_device(np.zeros((6, 1)))
    weighted = weights is not None and n > 0
    _accumulate_kernel[blocks, BLOCK](
        d_jacobian, d_residuals, f64(weights) if weighted else d_residuals, weighted, out
    )
    system = sum_partials(to_host(out))[0]
    if n == 0:  # the placeholder row above must not count
        return LinearSystem.empty()
    return system
