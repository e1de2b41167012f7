"""The 6x6 algebra of a Gauss-Newton step, compiled: kintinuous_ref.odometry.solve's `solve`,
`apply_increment` and `refine`, and combined's `joint_system` and `CombinedProblem`, with the same
signatures and the same steps.

The step runs on the host in both backends (paper IV-A.3). The reference spends about a hundred
NumPy calls on it, each microseconds of Python for nanoseconds of arithmetic: a joint system,
a solve and an increment take 78 microseconds there and 12 here (random systems), and the
odometry of a 640x480 frame (about 13 iterations) 1.2-2.0 ms less. LAPACK does the
decompositions in both (numba binds SciPy's copy); the small products and the triangular
solves are plain loops, which numba compiles in a fraction of the time of its array
expressions and of np.linalg.solve (about 4 s in all here instead of 11), and which equal
BLAS's and LAPACK's to rounding (tests/test_fast_solve.py).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence

import numba
import numpy as np

from kintinuous_ref import se3
from kintinuous_ref.config import TrackingConfig
from kintinuous_ref.odometry import combined as ref_combined
from kintinuous_ref.odometry import solve as ref_solve
from kintinuous_ref.odometry.solve import MAX_CONDITION, LinearSystem

_jit = numba.njit(cache=True)

# What _scaled_solution says of a system (kintinuous_ref.odometry.solve.solve's reasons).
SOLVED, NOT_FINITE, UNCONSTRAINED, ILL_CONDITIONED, NOT_DEFINITE = range(5)
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
        return None, f"too few correspondences ({system.count} < {min_count})"
    status, xi, condition = _scaled_solution(system.A, system.b)
    if status == SOLVED:
        return xi, ""
    reasons = {
        NOT_FINITE: "normal equations contain NaN or infinity",
        UNCONSTRAINED: "singular system (a degree of freedom has no constraint)",
        ILL_CONDITIONED: f"singular system (condition number {condition:.1e})",
        NOT_DEFINITE: "singular system (Cholesky failed)",
    }
    return None, reasons[status]


@_jit
def _product(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """a @ b of small matrices."""
    out = np.zeros((a.shape[0], b.shape[1]))
    for i in range(a.shape[0]):
        for k in range(a.shape[1]):
            for j in range(b.shape[1]):
                out[i, j] += a[i, k] * b[k, j]
    return out


@_jit
def _transposed(a: np.ndarray) -> np.ndarray:
    out = np.empty((a.shape[1], a.shape[0]))
    for i in range(a.shape[0]):
        for j in range(a.shape[1]):
            out[j, i] = a[i, j]
    return out


@_jit
def _column(v: np.ndarray) -> np.ndarray:
    """v as a (n, 1) matrix."""
    out = np.empty((len(v), 1))
    for i in range(len(v)):
        out[i, 0] = v[i]
    return out


@_jit
def _skew(x: float, y: float, z: float) -> np.ndarray:
    """kintinuous_ref.se3.skew of (x, y, z)."""
    m = np.zeros((3, 3))
    m[0, 1], m[0, 2] = -z, y
    m[1, 0], m[1, 2] = z, -x
    m[2, 0], m[2, 1] = -y, x
    return m


@_jit
def _exp(xi: np.ndarray) -> np.ndarray:
    """kintinuous_ref.se3.exp (eq. 4-5): Rodrigues' rotation and the left Jacobian V, their
    coefficients from the reference's own function (with its series near zero)."""
    theta = math.sqrt(xi[0] * xi[0] + xi[1] * xi[1] + xi[2] * xi[2])
    a, b, c = _so3_coefficients(theta)
    wx = _skew(xi[0], xi[1], xi[2])
    wx2 = _product(wx, wx)
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
    updated = _product(_exp(xi), pose)
    rotation = np.empty((3, 3))
    for i in range(3):
        for j in range(3):
            rotation[i, j] = updated[i, j]
    u, _, vt = np.linalg.svd(rotation)
    nearest = _product(u, vt)
    if _determinant(nearest) < 0:
        for i in range(3):
            u[i, 2] = -u[i, 2]
        nearest = _product(u, vt)
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


def apply_increment(xi: np.ndarray, pose: np.ndarray) -> np.ndarray:
    """T' = exp(xi) T (eq. 4), re-orthonormalised (kintinuous_ref.odometry.solve's)."""
    return _increment(np.asarray(xi, dtype=np.float64), np.ascontiguousarray(pose, np.float64))


def refine(
    pose: np.ndarray,
    system_at: Callable[[int, np.ndarray], LinearSystem],
    iterations: Sequence[int],
    min_count: int = 6,
    converged: float = TrackingConfig.converged_step,
) -> tuple[np.ndarray, str]:
    """kintinuous_ref.odometry.solve.refine with the compiled step."""
    return ref_solve.refine(
        pose, system_at, iterations, min_count, converged, step=(solve, apply_increment)
    )


@_jit
def _discounted_joint(
    icp_a: np.ndarray,
    icp_b: np.ndarray,
    icp_count: int,
    icp_weight: float,
    rgbd_a: np.ndarray,
    rgbd_b: np.ndarray,
    rgbd_weight: float,
    centre: np.ndarray,
    threshold: float,
) -> tuple:
    """(A, b) of joint_system's "degeneracy-aware" branch: the ICP system with its weak
    directions discounted (combined.discount_weak_directions, its information measured about
    `centre`) times `icp_weight`, plus the RGB-D system times `rgbd_weight`."""
    change = np.eye(6)  # combined.about_camera: [[I, 0], [skew(centre), I]]
    arm = _skew(centre[0], centre[1], centre[2])
    for i in range(3):
        for j in range(3):
            change[3 + i, j] = arm[i, j]
    centred = _product(_product(_transposed(change), icp_a), change)
    translational = max(centred[3, 3] + centred[4, 4] + centred[5, 5], 1e-300)
    rotational = max(centred[0, 0] + centred[1, 1] + centred[2, 2], 1e-300)
    lever = math.sqrt(rotational / translational)
    # D = diag(1 / lever x3, 1 x3); D C D / count and M D, entry by entry
    diagonal = np.ones(6)
    for i in range(3):
        diagonal[i] = 1 / lever
    information = np.empty((6, 6))
    to_scaled = np.empty((6, 6))
    for i in range(6):
        for j in range(6):
            information[i, j] = diagonal[i] * centred[i, j] * diagonal[j] / max(icp_count, 1)
            to_scaled[i, j] = change[i, j] * diagonal[j]
    eigenvalues, eigenvectors = np.linalg.eigh(information)
    kept = np.ones(6)
    weak = False
    if threshold > 0:
        for i in range(6):
            kept[i] = min(eigenvalues[i] / threshold, 1.0)
            weak = weak or kept[i] < 1.0
    a, b = icp_a, icp_b
    if weak:
        weighted = np.empty((6, 6))  # V diag(max(kept, 0))
        for i in range(6):
            for k in range(6):
                weighted[i, k] = eigenvectors[i, k] * max(kept[k], 0.0)
        shrink = _product(weighted, _transposed(eigenvectors))
        to_scaled_t = _transposed(to_scaled)
        a_eta = _product(shrink, _product(_product(to_scaled_t, icp_a), to_scaled))
        b_eta = _product(shrink, _product(to_scaled_t, _column(icp_b)))
        from_scaled = np.linalg.inv(to_scaled)
        from_scaled_t = _transposed(from_scaled)
        symmetric = np.empty((6, 6))
        for i in range(6):
            for j in range(6):
                symmetric[i, j] = (a_eta[i, j] + a_eta[j, i]) / 2
        a = _product(_product(from_scaled_t, symmetric), from_scaled)
        b = _product(from_scaled_t, b_eta)[:, 0]
    joint_a = np.empty((6, 6))
    joint_b = np.empty(6)
    for i in range(6):
        for j in range(6):
            joint_a[i, j] = a[i, j] * icp_weight + rgbd_a[i, j] * rgbd_weight
        joint_b[i] = b[i] * icp_weight + rgbd_b[i] * rgbd_weight
    return joint_a, joint_b


def joint_system(
    icp: LinearSystem,
    rgbd: LinearSystem,
    rgbd_weight: float = 1.0,
    weighting: str = "paper",
    original_code_icp_scale: float = 10.0,
    camera_position: np.ndarray | None = None,
    degeneracy_threshold: float = ref_combined.DEGENERACY_THRESHOLD,
) -> LinearSystem:
    """kintinuous_ref.odometry.combined.joint_system; the degeneracy-aware weightings (the
    default among them) compiled, the others (a scaling and a sum) the reference's."""
    if weighting != "degeneracy-aware" and weighting not in ref_combined.ROBUST_WEIGHTINGS:
        return ref_combined.joint_system(
            icp,
            rgbd,
            rgbd_weight,
            weighting,
            original_code_icp_scale,
            camera_position,
            degeneracy_threshold,
        )
    centre = np.zeros(3) if camera_position is None else camera_position
    icp_weight = 1.0 / ref_combined.icp_scale(icp) ** 2
    a, b = _discounted_joint(
        icp.A,
        icp.b,
        icp.count,
        icp_weight,
        rgbd.A,
        rgbd.b,
        float(rgbd_weight),
        np.ascontiguousarray(centre, dtype=np.float64),
        float(degeneracy_threshold),
    )
    cost = icp.cost * icp_weight + rgbd.cost * rgbd_weight
    return LinearSystem(a, b, icp.count + rgbd.count, cost)


class CombinedProblem(ref_combined.CombinedProblem):
    """kintinuous_ref.odometry.combined.CombinedProblem whose joint system is the compiled one."""

    combine = staticmethod(joint_system)
