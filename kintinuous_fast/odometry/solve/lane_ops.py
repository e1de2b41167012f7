"""The scalar algebra of a Gauss-Newton step on one lane, written once for the CPU and CUDA
targets (`build_lane_ops(jit)`, as in kintinuous_fast.targets): the products of small matrices
and their elements, the Jacobi rotation and the cyclic Jacobi eigensolver of the increment's
3x3, Cholesky and the triangular solves, and the increment itself (exp and the nearest
rotation). solve/ops.py builds the 6x6 steps a team of lanes runs on them.

Every intermediate lives in the caller's float64 `scratch` of shape (SCRATCH_MATRICES, 6, 6)
(solve/ops.py); which matrices each function uses is in its docstring.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from types import SimpleNamespace
from typing import Any

from kintinuous_ref import se3

__all__ = ["MAX_SWEEPS", "ROUNDING_SQUARED", "build_lane_ops"]

# Jacobi stops after this many sweeps (the tests' matrices need at most 6) ...
MAX_SWEEPS = 30
# ... or once the off-diagonal mass is below float64 rounding of the diagonal:
# sum_{p<q} a_pq^2 <= (2^-52)^2 sum_p a_pp^2.
ROUNDING_SQUARED = 2.0**-104
# Beyond this |cot 2 phi| the tangent of the Jacobi angle is 1 / (2 cot 2 phi) (theta^2 would
# overflow).
HUGE_COTANGENT = 1e150


def build_lane_ops(jit: Callable[[Any], Any]) -> SimpleNamespace:
    """The one-lane functions (module docstring) compiled with `jit`."""
    # The reference's series coefficients of exp (A, B, C of eq. 5), compiled as written.
    so3_coefficients = jit(se3._so3_coefficients)

    @jit
    def product(a: Any, b: Any, i: int, j: int, n: int) -> float:
        """(a @ b)[i, j] of the leading n x n blocks (matrices.product's order of sums)."""
        total = 0.0
        for k in range(n):
            total += a[i, k] * b[k, j]
        return total

    @jit
    def product_tn(a: Any, b: Any, i: int, j: int, n: int) -> float:
        """(a^T @ b)[i, j] of the leading n x n blocks."""
        total = 0.0
        for k in range(n):
            total += a[k, i] * b[k, j]
        return total

    @jit
    def product_nt(a: Any, b: Any, i: int, j: int, n: int) -> float:
        """(a @ b^T)[i, j] of the leading n x n blocks."""
        total = 0.0
        for k in range(n):
            total += a[i, k] * b[j, k]
        return total

    @jit
    def row_times(m: Any, v: Any, i: int, n: int) -> float:
        """(m @ v)[i] of the leading n entries."""
        total = 0.0
        for k in range(n):
            total += m[i, k] * v[k]
        return total

    @jit
    def column_times(m: Any, v: Any, i: int, n: int) -> float:
        """(m^T @ v)[i] of the leading n entries."""
        total = 0.0
        for k in range(n):
            total += m[k, i] * v[k]
        return total

    @jit
    def multiply(a: Any, b: Any, out: Any, n: int) -> None:
        """out = a @ b of the leading n x n blocks, on one lane."""
        for i in range(n):
            for j in range(n):
                out[i, j] = product(a, b, i, j, n)

    @jit
    def multiply_tn(a: Any, b: Any, out: Any, n: int) -> None:
        """out = a^T @ b of the leading n x n blocks, on one lane."""
        for i in range(n):
            for j in range(n):
                out[i, j] = product_tn(a, b, i, j, n)

    @jit
    def multiply_nt(a: Any, b: Any, out: Any, n: int) -> None:
        """out = a @ b^T of the leading n x n blocks, on one lane."""
        for i in range(n):
            for j in range(n):
                out[i, j] = product_nt(a, b, i, j, n)

    @jit
    def jacobi_rotation(app: float, aqq: float, apq: float) -> tuple[float, float, float]:
        """(t, c, s) of the rotation that zeroes a_pq (apq != 0): Golub and Van Loan's symmetric
        Schur step, t = tan phi, c = cos phi, s = sin phi."""
        theta = (aqq - app) / (2.0 * apq)
        if abs(theta) > HUGE_COTANGENT:
            t = 0.5 / theta
        else:
            t = 1.0 / (abs(theta) + math.sqrt(theta * theta + 1.0))
            if theta < 0.0:
                t = -t
        c = 1.0 / math.sqrt(t * t + 1.0)
        return t, c, t * c

    @jit
    def rotate(work: Any, vectors: Any, n: int, p: int, q: int) -> None:
        """One Jacobi rotation J (c, s in rows/columns p, q): work = J^T work J with
        work[p, q] = 0, vectors = vectors J."""
        apq = work[p, q]
        if apq == 0.0:
            return
        app = work[p, p]
        aqq = work[q, q]
        t, c, s = jacobi_rotation(app, aqq, apq)
        for k in range(n):
            if k != p and k != q:
                akp = work[k, p]
                akq = work[k, q]
                work[k, p] = c * akp - s * akq
                work[p, k] = work[k, p]
                work[k, q] = s * akp + c * akq
                work[q, k] = work[k, q]
        work[p, p] = app - t * apq
        work[q, q] = aqq + t * apq
        work[p, q] = 0.0
        work[q, p] = 0.0
        for k in range(n):
            vkp = vectors[k, p]
            vkq = vectors[k, q]
            vectors[k, p] = c * vkp - s * vkq
            vectors[k, q] = s * vkp + c * vkq

    @jit
    def off_diagonal_negligible(work: Any, n: int) -> bool:
        """Jacobi's stopping test on the leading n x n block (ROUNDING_SQUARED)."""
        off = 0.0
        diagonal = 0.0
        for p in range(n):
            diagonal += work[p, p] * work[p, p]
            for q in range(p + 1, n):
                off += work[p, q] * work[p, q]
        return off <= ROUNDING_SQUARED * diagonal

    @jit
    def jacobi(a: Any, n: int, values: Any, vectors: Any, work: Any) -> None:
        """Eigenvalues (ascending) and eigenvectors of the leading n x n block of `a` by cyclic
        Jacobi on one lane, its iterate in `work` (n x n): the increment's 3x3."""
        for i in range(n):
            for j in range(n):
                work[i, j] = a[i, j]
                vectors[i, j] = 1.0 if i == j else 0.0
        for _ in range(MAX_SWEEPS):
            if off_diagonal_negligible(work, n):
                break
            for p in range(n - 1):
                for q in range(p + 1, n):
                    rotate(work, vectors, n, p, q)
        for i in range(n):
            values[i] = work[i, i]
        for i in range(n - 1):  # selection sort, ascending, the columns of `vectors` along
            smallest = i
            for j in range(i + 1, n):
                if values[j] < values[smallest]:
                    smallest = j
            if smallest != i:
                value = values[i]
                values[i] = values[smallest]
                values[smallest] = value
                for k in range(n):
                    entry = vectors[k, i]
                    vectors[k, i] = vectors[k, smallest]
                    vectors[k, smallest] = entry

    @jit
    def cholesky(a: Any, n: int, lower: Any) -> bool:
        """lower (its upper triangle zeroed) with lower lower^T = a (n x n), as LAPACK's potrf:
        False at the first pivot that is not > 0 (NaN included), where np.linalg.cholesky
        raises."""
        for j in range(n):
            pivot = a[j, j]
            for k in range(j):
                pivot -= lower[j, k] * lower[j, k]
            if not (pivot > 0.0 and math.isfinite(pivot)):
                return False
            root = math.sqrt(pivot)
            lower[j, j] = root
            for i in range(j):
                lower[i, j] = 0.0
            for i in range(j + 1, n):
                total = a[i, j]
                for k in range(j):
                    total -= lower[i, k] * lower[j, k]
                lower[i, j] = total / root
        return True

    @jit
    def forward_substitution(lower: Any, rhs: Any, x: Any, n: int) -> None:
        """x with lower @ x = rhs (solve/__init__.py's _forward_substitution)."""
        for i in range(n):
            total = rhs[i]
            for j in range(i):
                total -= lower[i, j] * x[j]
            x[i] = total / lower[i, i]

    @jit
    def back_substitution(lower: Any, rhs: Any, x: Any, n: int) -> None:
        """x with lower^T @ x = rhs (solve/__init__.py's _back_substitution)."""
        for i in range(n - 1, -1, -1):
            total = rhs[i]
            for j in range(i + 1, n):
                total -= lower[j, i] * x[j]
            x[i] = total / lower[i, i]

    @jit
    def determinant3(m: Any) -> float:
        """det of the leading 3x3 block, expanded along its first row (solve's _determinant)."""
        return (
            m[0, 0] * (m[1, 1] * m[2, 2] - m[1, 2] * m[2, 1])
            - m[0, 1] * (m[1, 0] * m[2, 2] - m[1, 2] * m[2, 0])
            + m[0, 2] * (m[1, 0] * m[2, 1] - m[1, 1] * m[2, 0])
        )

    @jit
    def exp(xi: Any, pose: Any, scratch: Any) -> None:
        """pose (4x4) = exp(xi) (eq. 4-5): Rodrigues' rotation and the left Jacobian V, the
        coefficients the reference's (solve/__init__.py's _exp). Uses scratch[1:3]."""
        theta = math.sqrt(xi[0] * xi[0] + xi[1] * xi[1] + xi[2] * xi[2])
        a, b, c = so3_coefficients(theta)
        wx = scratch[1]
        for i in range(3):
            wx[i, i] = 0.0
        wx[0, 1] = -xi[2]
        wx[0, 2] = xi[1]
        wx[1, 0] = xi[2]
        wx[1, 2] = -xi[0]
        wx[2, 0] = -xi[1]
        wx[2, 1] = xi[0]
        wx2 = scratch[2]
        multiply(wx, wx, wx2, 3)
        for i in range(3):
            translation = 0.0
            for j in range(3):
                identity = 1.0 if i == j else 0.0
                pose[i, j] = identity + a * wx[i, j] + b * wx2[i, j]
                translation += (identity + b * wx[i, j] + c * wx2[i, j]) * xi[3 + j]
            pose[i, 3] = translation
            pose[3, i] = 0.0
        pose[3, 3] = 1.0

    @jit
    def increment(xi: Any, pose: Any, out: Any, scratch: Any) -> None:
        """out (4x4) = exp(xi) pose (eq. 4) with its rotation block replaced by the nearest
        rotation: solve/__init__.py's _increment. Its SVD R = U S V^T becomes the polar
        decomposition U V^T = R (R^T R)^-1/2 through Jacobi on R^T R = V S^2 V^T; where that
        has det < 0 the column of U of the smallest singular value changes sign, as there.
        Uses scratch[0:6]."""
        exp(xi, scratch[3], scratch)
        multiply(scratch[3], pose, out, 4)
        gram = scratch[1]  # R^T R
        multiply_tn(out, out, gram, 3)
        squares = scratch[4][0]  # S^2, ascending
        right = scratch[5]  # V
        jacobi(gram, 3, squares, right, scratch[0])
        left = scratch[2]  # U = R V S^-1
        for j in range(3):
            singular = math.sqrt(max(squares[j], 1e-300))
            for i in range(3):
                left[i, j] = product(out, right, i, j, 3) / singular
        nearest = scratch[3]
        multiply_nt(left, right, nearest, 3)
        if determinant3(nearest) < 0:
            for i in range(3):
                left[i, 0] = -left[i, 0]
            multiply_nt(left, right, nearest, 3)
        for i in range(3):
            for j in range(3):
                out[i, j] = nearest[i, j]

    return SimpleNamespace(  # what the team's steps (ops.py) build on; the rest is internal
        product=product,
        product_tn=product_tn,
        product_nt=product_nt,
        row_times=row_times,
        column_times=column_times,
        jacobi_rotation=jacobi_rotation,
        off_diagonal_negligible=off_diagonal_negligible,
        cholesky=cholesky,
        forward_substitution=forward_substitution,
        back_substitution=back_substitution,
        increment=increment,
    )
