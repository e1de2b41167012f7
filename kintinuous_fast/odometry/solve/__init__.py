"""The 6x6 algebra of a Gauss-Newton step, compiled for the host: kintinuous_ref.odometry.solve's
`solve`, `apply_increment` and `refine`, with the same signatures and the same steps.

The step runs on the host in both backends (paper IV-A.3): the reference spends about a hundred
NumPy calls on it, each microseconds of Python for nanoseconds of arithmetic (docs/benchmarks.md
has the cost per frame). LAPACK does the decompositions in both (numba binds SciPy's copy); the
small products (solve/matrices.py) and the triangular solves are plain loops, which numba
compiles in a fraction of the time of its array expressions and of np.linalg.solve, and which
equal BLAS's and LAPACK's to rounding (tests/test_fast_solve.py). Each target's module
(solve/cpu.py, solve/cuda.py) adds its `accumulate` and mirrors kintinuous_ref.odometry.solve.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence

import numba
import numpy as np

from kintinuous_ref import se3
from kintinuous_ref.config import TrackingConfig
from kintinuous_ref.odometry import solve as ref_solve
from kintinuous_ref.odometry.solve import MAX_CONDITION, LinearSystem

from .matrices import product, skew

__all__ = ["apply_increment", "refine", "solve"]
# What each target's module (solve/cpu.py, solve/cuda.py) exports: kintinuous_ref.odometry.solve's
# own LinearSystem and plausibility test, this module's compiled step and its own `accumulate`.
TARGET_ALL = ["LinearSystem", "accumulate", *__all__, "implausible_motion"]

_jit = numba.njit(cache=True)

# What _scaled_solution says of a system (kintinuous_ref.odometry.solve.solve's reasons).
SOLVED, NOT_FINITE, UNCONSTRAINED, ILL_CONDITIONED, NOT_DEFINITE = range(5)
# A status beside those: fewer pairs than the least count, before any solution is tried.
TOO_FEW = 10
# The reference's scalar maths, compiled as it is written (one body for both).
_so3_coefficients = _jit(se3._so3_coefficients)


@_jit
def _scaled_solution(A: np.ndarray, b: np.ndarray) -> tuple:
    """(status, xi, condition) of A xi = -b, solved as the reference solves it: Jacobi-scaled,
    the condition number from the scaled matrix's eigenvalues, then Cholesky."""
    xi = np.zeros(6)
    for i in range(6):
        for j in range(6):
            if not math.isfinite(A[i, j]):
                return NOT_FINITE, xi, 0.0
        if not math.isfinite(b[i]):
            return NOT_FINITE, xi, 0.0
    for i in range(6):
        if A[i, i] <= 0:
            return UNCONSTRAINED, xi, 0.0
    scale = np.empty(6)
    for i in range(6):
        scale[i] = 1.0 / math.sqrt(A[i, i])
    scaled = np.empty((6, 6))
    for i in range(6):
        for j in range(6):
            scaled[i, j] = A[i, j] * scale[i] * scale[j]
    eigenvalues = np.linalg.eigvalsh(scaled)
    if eigenvalues[0] <= eigenvalues[-1] / MAX_CONDITION:
        return ILL_CONDITIONED, xi, eigenvalues[-1] / max(eigenvalues[0], 1e-300)
    try:
        factor = np.linalg.cholesky(scaled)
    except Exception:  # noqa: BLE001 (numba catches no narrower class)
        return NOT_DEFINITE, xi, 0.0
    # (D^-1/2 A D^-1/2) y = -D^-1/2 b through L L^T, then xi = D^-1/2 y (the reference hands
    # each triangle to np.linalg.solve).
    rhs = np.empty(6)
    for i in range(6):
        rhs[i] = -b[i] * scale[i]
    y = _back_substitution(factor, _forward_substitution(factor, rhs))
    for i in range(6):
        xi[i] = y[i] * scale[i]
    return SOLVED, xi, 0.0


@_jit
def _forward_substitution(lower: np.ndarray, rhs: np.ndarray) -> np.ndarray:
    """x with lower @ x = rhs, `lower` lower-triangular."""
    x = np.empty_like(rhs)
    for i in range(len(rhs)):
        total = rhs[i]
        for j in range(i):
            total -= lower[i, j] * x[j]
        x[i] = total / lower[i, i]
    return x


@_jit
def _back_substitution(lower: np.ndarray, rhs: np.ndarray) -> np.ndarray:
    """x with lower.T @ x = rhs, `lower` lower-triangular."""
    x = np.empty_like(rhs)
    for i in range(len(rhs) - 1, -1, -1):
        total = rhs[i]
        for j in range(i + 1, len(rhs)):
            total -= lower[j, i] * x[j]
        x[i] = total / lower[i, i]
    return x


def solve(system: LinearSystem, min_count: int = 6) -> tuple[np.ndarray | None, str]:
    """kintinuous_ref.odometry.solve.solve: the increment xi with A xi = -b, or (None, reason)."""
    if system.count < min_count:
        return None, failure_reason(TOO_FEW, 0.0, system.count, min_count)
    status, xi, condition = _scaled_solution(system.A, system.b)
    if status == SOLVED:
        return xi, ""
    return None, failure_reason(status, condition, system.count, min_count)


def failure_reason(status: int, condition: float, count: int, min_count: int) -> str:
    """The reason, in the reference's words, of a step that failed with `status` (TOO_FEW or
    one of _scaled_solution's), `condition` its scaled matrix's condition number and `count`
    its pairs."""
    if status == TOO_FEW:
        return f"too few correspondences ({count} < {min_count})"
    return solve_reasons(condition)[status]


def solve_reasons(condition: float) -> dict[int, str]:
    """The reference's reason for each failed status of _scaled_solution (`condition`: the
    scaled matrix's condition number where it is ILL_CONDITIONED)."""
    return {
        NOT_FINITE: "normal equations contain NaN or infinity",
        UNCONSTRAINED: "singular system (a degree of freedom has no constraint)",
        ILL_CONDITIONED: f"singular system (condition number {condition:.1e})",
        NOT_DEFINITE: "singular system (Cholesky failed)",
    }


@_jit
def _exp(xi: np.ndarray) -> np.ndarray:
    """kintinuous_ref.se3.exp (eq. 4-5): Rodrigues' rotation and the left Jacobian V, their
    coefficients from the reference's own function (with its series near zero)."""
    theta = math.sqrt(xi[0] * xi[0] + xi[1] * xi[1] + xi[2] * xi[2])
    a, b, c = _so3_coefficients(theta)
    wx = skew(xi[0], xi[1], xi[2])
    wx2 = product(wx, wx)
    pose = np.eye(4)
    for i in range(3):
        translation = 0.0
        for j in range(3):
            identity = 1.0 if i == j else 0.0
            pose[i, j] = identity + a * wx[i, j] + b * wx2[i, j]
            translation += (identity + b * wx[i, j] + c * wx2[i, j]) * xi[3 + j]
        pose[i, 3] = translation
    return pose


@_jit
def _increment(xi: np.ndarray, pose: np.ndarray) -> np.ndarray:
    """exp(xi) pose with its rotation replaced by the nearest one (se3.orthonormalize: SVD)."""
    updated = product(_exp(xi), pose)
    rotation = np.empty((3, 3))
    for i in range(3):
        for j in range(3):
            rotation[i, j] = updated[i, j]
    u, _, vt = np.linalg.svd(rotation)
    nearest = product(u, vt)
    if _determinant(nearest) < 0:
        for i in range(3):
            u[i, 2] = -u[i, 2]
        nearest = product(u, vt)
    for i in range(3):
        for j in range(3):
            updated[i, j] = nearest[i, j]
    return updated


@_jit
def _determinant(m: np.ndarray) -> float:
    """det of a 3x3 matrix, expanded along its first row."""
    return (
        m[0, 0] * (m[1, 1] * m[2, 2] - m[1, 2] * m[2, 1])
        - m[0, 1] * (m[1, 0] * m[2, 2] - m[1, 2] * m[2, 0])
        + m[0, 2] * (m[1, 0] * m[2, 1] - m[1, 1] * m[2, 0])
    )


@_jit
def gauss_newton_step(  # noqa: ANN201 (a tuple of numba's types)
    a: np.ndarray, b: np.ndarray, count: int, min_count: int, pose: np.ndarray
):
    """One step of refine after its system (A, b, count), in compiled code: solve, then
    apply_increment. (status, condition, the new pose, |xi|): SOLVED, or TOO_FEW or a status of
    _scaled_solution with the pose unchanged (failure_reason words it)."""
    if count < min_count:
        return TOO_FEW, 0.0, pose, 0.0
    status, xi, condition = _scaled_solution(a, b)
    if status != SOLVED:
        return status, condition, pose, 0.0
    # |xi| as np.linalg.norm computes it: the square root of the dot product
    return SOLVED, 0.0, _increment(xi, pose), math.sqrt(np.dot(xi, xi))


def apply_increment(xi: np.ndarray, pose: np.ndarray) -> np.ndarray:
    """T' = exp(xi) T (eq. 4), re-orthonormalised (kintinuous_ref.odometry.solve's)."""
    return _increment(np.asarray(xi, dtype=np.float64), np.ascontiguousarray(pose, np.float64))


def refine(
    pose: np.ndarray,
    system_at: Callable[[int, np.ndarray], LinearSystem],
    iterations: Sequence[int],
    min_count: int = 6,
    converged: float = TrackingConfig.converged_step,
    step: tuple[Callable, Callable] | None = None,
) -> tuple[np.ndarray, str]:
    """kintinuous_ref.odometry.solve.refine with the compiled step of this module unless `step`
    names another. Where `system_at` is the `system` of a problem whose levels run whole in
    compiled code (its `refine_level`: the CPU's joint ICP + RGB-D, ICP and RGB-D problems),
    each level runs there, with no Python between its steps; the levels it declines (None) and
    any other problem go through the reference's loop, level by level."""
    step = step or (solve, apply_increment)
    problem = getattr(system_at, "__self__", None)
    refine_level = getattr(problem, "refine_level", None)
    if refine_level is None or step != (solve, apply_increment):
        return ref_solve.refine(pose, system_at, iterations, min_count, converged, step)
    for level in reversed(range(len(iterations))):
        steps = iterations[level]
        result = refine_level(level, pose, steps, min_count, converged) if steps else None
        if result is None:
            only = [steps if at == level else 0 for at in range(len(iterations))]
            result = ref_solve.refine(pose, system_at, only, min_count, converged, step)
        elif result[1]:
            result = (result[0], f"level {level}: {result[1]}")
        pose, reason = result
        if reason:
            return pose, reason
    return pose, ""
