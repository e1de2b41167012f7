"""Gauss-Newton building blocks shared by the dense estimators (paper eq. 3-5, 12-13).

Every dense estimator linearises its cost around the current pose estimate T and produces rows
J_k (1x6) and residuals r_k, one per correspondence; one step minimises ||J xi + r||^2, i.e. solves
the 6x6 normal equations

    (J^T J) xi = -J^T r,                                                    (eq. 12-13)

accumulated in double precision (float32 sums over 300 000 pixels lose the small increments) and
solved by Cholesky. The increment is applied on the left, T' = exp(xi) T (eq. 4). Both ICP and
RGB-D use the same twist: the left perturbation of the camera-to-world pose, expressed in the
world frame, so their systems can simply be added (eq. 11).

A system can fail: too few correspondences, a singular or badly conditioned matrix (a single
plane constrains only three of six degrees of freedom), or an implausibly large step. Those cases
return a reason instead of an increment; the trackers turn them into TrackingResult.ok = False.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from kintinuous_ref import se3
from kintinuous_ref.config import TrackingConfig

# A system whose scaled condition number exceeds this has (numerically) lost at least one degree of
# freedom: its increment along that direction would be noise amplified by the inverse.
MAX_CONDITION = 1e10


@dataclass
class LinearSystem:
    """Normal equations A xi = -b of one Gauss-Newton step, with bookkeeping."""

    A: np.ndarray  # (6, 6) float64, J^T W J
    b: np.ndarray  # (6,) float64, J^T W r
    count: int  # correspondences that contributed
    cost: float  # sum of the weighted squared residuals, r^T W r

    @staticmethod
    def empty() -> LinearSystem:
        return LinearSystem(np.zeros((6, 6)), np.zeros(6), 0, 0.0)

    def __add__(self, other: LinearSystem) -> LinearSystem:
        return LinearSystem(
            self.A + other.A, self.b + other.b, self.count + other.count, self.cost + other.cost
        )

    def scaled(self, a_scale: float, b_scale: float | None = None) -> LinearSystem:
        """The system of the cost multiplied by `a_scale` (b by `b_scale`, default the same).

        A separate b scale exists only to reproduce the original code's inconsistent weighting
        (combined.py); a consistent cost scaling uses one factor for both.
        """
        b_scale = a_scale if b_scale is None else b_scale
        return LinearSystem(self.A * a_scale, self.b * b_scale, self.count, self.cost * a_scale)


def accumulate(
    jacobian: np.ndarray, residuals: np.ndarray, weights: np.ndarray | None = None
) -> LinearSystem:
    """Normal equations of the Jacobian `jacobian` (6, N) and `residuals` (N,), in float64.

    The Jacobian is stored as columns, one per correspondence (the layout the estimators build
    it in). `weights` (N,) multiply each squared residual (IRLS weights); None means all ones.
    One product of the (7, N) matrix [J^T; r^T] with itself gives A, b and the cost at once.
    """
    stacked = np.vstack([jacobian, residuals[None, :]]).astype(np.float64, copy=False)
    weighted = stacked if weights is None else stacked * weights[None, :]
    product = weighted @ stacked.T
    return LinearSystem(product[:6, :6], product[:6, 6], len(residuals), float(product[6, 6]))


def solve(system: LinearSystem, min_count: int = 6) -> tuple[np.ndarray | None, str]:
    """The Gauss-Newton increment xi with A xi = -b, or (None, reason) when there is none.

    The condition number is measured on the Jacobi-scaled matrix D^-1/2 A D^-1/2, which does not
    depend on the units of rotation (radians) versus translation (metres); only a real loss of a
    degree of freedom makes it large.
    """
    if system.count < min_count:
        return None, f"too few correspondences ({system.count} < {min_count})"
    A, b = system.A, system.b
    if not (np.all(np.isfinite(A)) and np.all(np.isfinite(b))):
        return None, "normal equations contain NaN or infinity"
    diagonal = np.diag(A)
    if np.any(diagonal <= 0):
        return None, "singular system (a degree of freedom has no constraint)"
    scale = 1.0 / np.sqrt(diagonal)
    scaled = A * scale[:, None] * scale[None, :]
    eigenvalues = np.linalg.eigvalsh(scaled)
    if eigenvalues[0] <= eigenvalues[-1] / MAX_CONDITION:
        condition = eigenvalues[-1] / max(eigenvalues[0], 1e-300)
        return None, f"singular system (condition number {condition:.1e})"
    try:
        factor = np.linalg.cholesky(scaled)
    except np.linalg.LinAlgError:
        return None, "singular system (Cholesky failed)"
    # Solve (D^-1/2 A D^-1/2) y = -D^-1/2 b with the Cholesky factor L L^T, then xi = D^-1/2 y.
    y = np.linalg.solve(factor.T, np.linalg.solve(factor, -b * scale))
    return y * scale, ""


def apply_increment(xi: np.ndarray, pose: np.ndarray) -> np.ndarray:
    """T' = exp(xi) T (eq. 4), re-orthonormalised so that thousands of products stay rigid."""
    updated = se3.exp(xi) @ pose
    updated[:3, :3] = se3.orthonormalize(updated[:3, :3])
    return updated


def implausible_motion(
    increment: np.ndarray, max_translation: float, max_rotation_deg: float
) -> str:
    """'' when a relative motion (4x4) is a plausible frame-to-frame step, else the reason."""
    if not np.all(np.isfinite(increment)):
        return "pose estimate is NaN"
    translation = float(np.linalg.norm(increment[:3, 3]))
    angle = float(np.degrees(se3.rotation_angle(increment[:3, :3])))
    if translation > max_translation:
        return f"implausible jump: {translation:.3f} m in one frame (> {max_translation} m)"
    if angle > max_rotation_deg:
        return f"implausible jump: {angle:.1f} deg in one frame (> {max_rotation_deg} deg)"
    return ""


def refine(
    pose: np.ndarray,
    system_at: Callable[[int, np.ndarray], LinearSystem],
    iterations: Sequence[int],
    min_count: int = 6,
    converged: float = TrackingConfig.converged_step,
    step: tuple[Callable, Callable] | None = None,
) -> tuple[np.ndarray, str]:
    """Coarse-to-fine Gauss-Newton: at most `iterations[l]` steps at level l, coarsest first.

    `system_at(level, pose)` builds the normal equations at a level for a pose estimate. Returns
    the refined pose and '' or, at the first step without a solution, the pose so far and why.
    A step shorter than `converged` (twist norm; the trackers pass tracking.converged_step) ends
    the level early: the steps after it would move the pose by less than about as much again.
    `step` = (solve, apply_increment) as this module's (the default), or functions that compute
    the same (a fast backend's compiled ones).
    """
    solve_system, update = step or (solve, apply_increment)
    for level in reversed(range(len(iterations))):
        for _ in range(iterations[level]):
            xi, reason = solve_system(system_at(level, pose), min_count)
            if xi is None:
                return pose, f"level {level}: {reason}"
            pose = update(xi, pose)
            if float(np.linalg.norm(xi)) < converged:
                break
    return pose, ""
