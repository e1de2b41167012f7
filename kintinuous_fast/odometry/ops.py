"""The per-element geometry both estimators share, written once for the CPU and CUDA targets.

`build_ops(jit)` (the pattern of kintinuous_fast.targets) defines the rigid transform of one
point, its rotation alone, and the rounding to a pixel, compiled with the decorator it is given.
Each target compiles them once (odometry/sums/cpu.py, odometry/sums/cuda.py) and hands them to
the ICP and RGB-D factories (icp/ops.py, rgbd/ops.py), whose functions call them.

Precision: the reference computes every per-correspondence quantity in float64 (its maps are
float32, converted once); so do these functions and those built on them (values read from
arrays go through float()). Each formula is written in the reference's order of operations, so
the rows agree to the last bit up to FMA contraction and the order of the 3-term dot products
inside NumPy's matrix products (~1 ulp). Only the sums over all rows differ in order (chunked
partials on the CPU, block trees on CUDA, BLAS in the reference): relative differences ~1e-15
of the largest terms.
"""

from __future__ import annotations

from collections.abc import Callable
from types import SimpleNamespace
from typing import Any

from kintinuous_fast.targets import build_rint


def build_ops(jit: Callable[[Any], Any]) -> SimpleNamespace:
    """rint, transform and rotate compiled with `jit` (see kintinuous_fast.targets)."""

    rint = build_rint(jit)[0]

    @jit
    def transform(m: Any, x: float, y: float, z: float) -> tuple[float, float, float]:
        """The rigid transform of the 4x4 (or 3x4) float64 matrix m applied to (x, y, z)."""
        return (
            m[0, 0] * x + m[0, 1] * y + m[0, 2] * z + m[0, 3],
            m[1, 0] * x + m[1, 1] * y + m[1, 2] * z + m[1, 3],
            m[2, 0] * x + m[2, 1] * y + m[2, 2] * z + m[2, 3],
        )

    @jit
    def rotate(m: Any, x: float, y: float, z: float) -> tuple[float, float, float]:
        """The rotation part of m applied to (x, y, z)."""
        return (
            m[0, 0] * x + m[0, 1] * y + m[0, 2] * z,
            m[1, 0] * x + m[1, 1] * y + m[1, 2] * z,
            m[2, 0] * x + m[2, 1] * y + m[2, 2] * z,
        )

    return SimpleNamespace(rint=rint, transform=transform, rotate=rotate)
