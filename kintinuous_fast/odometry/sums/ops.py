"""The accumulated normal equations (odometry/sums) element by element, written once for the CPU
and CUDA targets: `build_ops(jit)` as in kintinuous_fast.targets."""

from __future__ import annotations

from collections.abc import Callable
from types import SimpleNamespace
from typing import Any

from . import NV


def build_ops(jit: Callable[[Any], Any]) -> SimpleNamespace:
    """zero, add_row and add_column compiled with `jit`."""

    @jit
    def zero(acc: Any) -> None:
        """acc[:] = 0 for a thread's NV sums."""
        for s in range(NV):
            acc[s] = 0.0

    @jit
    def add_row(acc: Any, jacobian: tuple, r: float, w: float) -> None:
        """acc += w [J^T J (upper triangle), J^T r, r^2, 1] for one row (ref accumulate), J =
        `jacobian` (j0..j5)."""
        j0, j1, j2, j3, j4, j5 = jacobian
        a0 = w * j0
        a1 = w * j1
        a2 = w * j2
        a3 = w * j3
        a4 = w * j4
        a5 = w * j5
        acc[0] += a0 * j0
        acc[1] += a0 * j1
        acc[2] += a0 * j2
        acc[3] += a0 * j3
        acc[4] += a0 * j4
        acc[5] += a0 * j5
        acc[6] += a1 * j1
        acc[7] += a1 * j2
        acc[8] += a1 * j3
        acc[9] += a1 * j4
        acc[10] += a1 * j5
        acc[11] += a2 * j2
        acc[12] += a2 * j3
        acc[13] += a2 * j4
        acc[14] += a2 * j5
        acc[15] += a3 * j3
        acc[16] += a3 * j4
        acc[17] += a3 * j5
        acc[18] += a4 * j4
        acc[19] += a4 * j5
        acc[20] += a5 * j5
        acc[21] += a0 * r
        acc[22] += a1 * r
        acc[23] += a2 * r
        acc[24] += a3 * r
        acc[25] += a4 * r
        acc[26] += a5 * r
        acc[27] += w * r * r
        acc[28] += 1.0

    @jit
    def add_column(acc: Any, jacobian: Any, k: int, r: float, w: float) -> None:
        """add_row of the row stored as column k of a (6, N) `jacobian` (ref accumulate's
        layout)."""
        row = (
            jacobian[0, k],
            jacobian[1, k],
            jacobian[2, k],
            jacobian[3, k],
            jacobian[4, k],
            jacobian[5, k],
        )
        add_row(acc, row, r, w)

    return SimpleNamespace(zero=zero, add_row=add_row, add_column=add_column)
