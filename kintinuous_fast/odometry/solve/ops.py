"""The 6x6 algebra of a Gauss-Newton step as scalar loops, written once for the CPU and CUDA
targets: `build_ops(jit)` as in kintinuous_fast.targets. What solve/__init__.py and
odometry/combined.py compute on the host with LAPACK and fresh arrays (eigh, cholesky, svd, inv),
here without allocation, np.linalg or exceptions, so that a CUDA kernel can run the whole
iteration on the device: cyclic Jacobi for the symmetric eigenproblems, Cholesky and the two
triangular solves for the normal equations, the polar decomposition for the nearest rotation.

Every intermediate lives in the caller's float64 `scratch` of shape (SCRATCH_MATRICES, 6, 6) (in
a CUDA kernel `cuda.local.array((SCRATCH_MATRICES, 6, 6), float64)`); vectors use rows of its
matrices. Which matrices each function uses is in its docstring; the arguments must not be views
of them, nor of each other.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from types import SimpleNamespace
from typing import Any

from kintinuous_ref import se3
from kintinuous_ref.odometry.solve import MAX_CONDITION

from . import ILL_CONDITIONED, NOT_DEFINITE, NOT_FINITE, SOLVED, UNCONSTRAINED

__all__ = ["SCRATCH_MATRICES", "build_ops"]

# The (6, 6) float64 matrices a caller's scratch holds: discounted_joint and increment use all.
SCRATCH_MATRICES = 6
# Cyclic Jacobi stops after this many sweeps (the tests' matrices need at most 6) ...
MAX_SWEEPS = 30
# ... or once the off-diagonal mass is below float64 rounding of the diagonal:
# sum_{p<q} a_pq^2 <= (2^-52)^2 sum_p a_pp^2.
ROUNDING_SQUARED = 2.0**-104
# Beyond this |cot 2 phi| the tangent of the Jacobi angle is 1 / (2 cot 2 phi) (theta^2 would
# overflow).
HUGE_COTANGENT = 1e150


def build_ops(jit: Callable[[Any], Any]) -> SimpleNamespace:
    """symmetric_eigen, scaled_solution, discounted_joint and increment (and the Cholesky
    factorisation they use) compiled with `jit`."""
    # The reference's series coefficients of exp (A, B, C of eq. 5), compiled as written.
    so3_coefficients = jit(se3._so3_coefficients)

    @jit
    def multiply(a: Any, b: Any, out: Any, n: int) -> None:
        """out = a @ b of the leading n x n blocks (matrices.product's order of sums)."""
        for i in range(n):
            for j in range(n):
                total = 0.0
                for k in range(n):
                    total += a[i, k] * b[k, j]
                out[i, j] = total

    @jit
    def multiply_tn(a: Any, b: Any, out: Any, n: int) -> None:
        """out = a^T @ b of the leading n x n blocks."""
        for i in range(n):
            for j in range(n):
                total = 0.0
                for k in range(n):
                    total += a[k, i] * b[k, j]
                out[i, j] = total

    @jit
    def multiply_nt(a: Any, b: Any, out: Any, n: int) -> None:
        """out = a @ b^T of the leading n x n blocks."""
        for i in range(n):
            for j in range(n):
                total = 0.0
                for k in range(n):
                    total += a[i, k] * b[j, k]
                out[i, j] = total

    @jit
    def rotate(work: Any, vectors: Any, n: int, p: int, q: int) -> None:
        """One Jacobi rotation J (c, s in rows/columns p, q): work = J^T work J with
        work[p, q] = 0, vectors = vectors J (Golub and Van Loan's symmetric Schur step)."""
        apq = work[p, q]
        if apq == 0.0:
            return
        app = work[p, p]
        aqq = work[q, q]
        theta = (aqq - app) / (2.0 * apq)
        if abs(theta) > HUGE_COTANGENT:
            t = 0.5 / theta
        else:
            t = 1.0 / (abs(theta) + math.sqrt(theta * theta + 1.0))
            if theta < 0.0:
                t = -t
        c = 1.0 / math.sqrt(t * t + 1.0)
        s = t * c
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
    def jacobi(a: Any, n: int, values: Any, vectors: Any, work: Any) -> None:
        """symmetric_eigen of the leading n x n block of `a`, its iterate in `work` (n x n)."""
        for i in range(n):
            for j in range(n):
                work[i, j] = a[i, j]
                vectors[i, j] = 1.0 if i == j else 0.0
        for _ in range(MAX_SWEEPS):
            off = 0.0
            diagonal = 0.0
            for p in range(n):
                diagonal += work[p, p] * work[p, p]
                for q in range(p + 1, n):
                    off += work[p, q] * work[p, q]
            if off <= ROUNDING_SQUARED * diagonal:
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
    def symmetric_eigen(a: Any, values: Any, vectors: Any, scratch: Any) -> None:
        """np.linalg.eigh of the symmetric n x n `a` (n = a.shape[0] <= 6; `a` unchanged):
        eigenvalues ascending into `values` (n,), unit eigenvectors as the columns of `vectors`
        (n, n), by cyclic Jacobi. Uses scratch[0]."""
        jacobi(a, a.shape[0], values, vectors, scratch[0])

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
    def scaled_solution(A: Any, b: Any, xi: Any, scratch: Any) -> tuple[int, float]:
        """(status, condition) of the normal equations A xi = -b (eq. 12-13), xi (6,) written
        (zeros unless SOLVED): solve/__init__.py's _scaled_solution, its checks in its order.
        Jacobi-scaled (D^-1/2 A D^-1/2), the condition from the scaled matrix's eigenvalues,
        then Cholesky. Uses scratch[0:5]: 1 the scaled matrix, 2 its eigenvectors, 3 the
        Cholesky factor, 4's rows the scale, the eigenvalues and the two triangular solves."""
        for i in range(6):
            xi[i] = 0.0
        for i in range(6):
            for j in range(6):
                if not math.isfinite(A[i, j]):
                    return NOT_FINITE, 0.0
            if not math.isfinite(b[i]):
                return NOT_FINITE, 0.0
        for i in range(6):
            if A[i, i] <= 0:
                return UNCONSTRAINED, 0.0
        scaled = scratch[1]
        rows = scratch[4]
        scale = rows[0]
        for i in range(6):
            scale[i] = 1.0 / math.sqrt(A[i, i])
        for i in range(6):
            for j in range(6):
                scaled[i, j] = A[i, j] * scale[i] * scale[j]
        eigenvalues = rows[1]
        symmetric_eigen(scaled, eigenvalues, scratch[2], scratch)
        if eigenvalues[0] <= eigenvalues[5] / MAX_CONDITION:
            return ILL_CONDITIONED, eigenvalues[5] / max(eigenvalues[0], 1e-300)
        factor = scratch[3]
        if not cholesky(scaled, 6, factor):
            return NOT_DEFINITE, 0.0
        # (D^-1/2 A D^-1/2) y = -D^-1/2 b through L L^T, then xi = D^-1/2 y
        rhs = rows[2]
        for i in range(6):
            rhs[i] = -b[i] * scale[i]
        forward_substitution(factor, rhs, rows[3], 6)
        back_substitution(factor, rows[3], rhs, 6)
        for i in range(6):
            xi[i] = rhs[i] * scale[i]
        return SOLVED, 0.0

    @jit
    def discounted_joint(
        icp_a: Any,
        icp_b: Any,
        icp_count: int,
        icp_weight: float,
        rgbd_a: Any,
        rgbd_b: Any,
        rgbd_weight: float,
        cx: float,
        cy: float,
        cz: float,
        threshold: float,
        out_a: Any,
        out_b: Any,
        scratch: Any,
    ) -> None:
        """(out_a, out_b) = combined.py's _discounted_joint (the joint normal equations of
        eq. 12-13, "degeneracy-aware"): the ICP system with its weak directions discounted, its
        information measured about the centre (cx, cy, cz), times `icp_weight`, plus the RGB-D
        system times `rgbd_weight`. Uses scratch[0:6]."""
        change = scratch[5]  # M = [[I, 0], [skew(c), I]] (combined.about_camera)
        for i in range(6):
            for j in range(6):
                change[i, j] = 1.0 if i == j else 0.0
        change[3, 1] = -cz
        change[3, 2] = cy
        change[4, 0] = cz
        change[4, 2] = -cx
        change[5, 0] = -cy
        change[5, 1] = cx
        multiply_tn(change, icp_a, scratch[1], 6)
        centred = scratch[2]  # M^T A M
        multiply(scratch[1], change, centred, 6)
        translational = max(centred[3, 3] + centred[4, 4] + centred[5, 5], 1e-300)
        rotational = max(centred[0, 0] + centred[1, 1] + centred[2, 2], 1e-300)
        lever = math.sqrt(rotational / translational)
        rows = scratch[4]
        diagonal = rows[0]  # D = diag(1 / lever x3, 1 x3)
        for i in range(6):
            diagonal[i] = 1 / lever if i < 3 else 1.0
        information = scratch[1]  # D C D / count
        to_scaled = scratch[3]  # M D
        for i in range(6):
            for j in range(6):
                information[i, j] = diagonal[i] * centred[i, j] * diagonal[j] / max(icp_count, 1)
                to_scaled[i, j] = change[i, j] * diagonal[j]
        eigenvalues = rows[1]
        eigenvectors = scratch[2]
        symmetric_eigen(information, eigenvalues, eigenvectors, scratch)
        kept = rows[2]
        weak = False
        for i in range(6):
            kept[i] = 1.0
        if threshold > 0:
            for i in range(6):
                kept[i] = min(eigenvalues[i] / threshold, 1.0)
                weak = weak or kept[i] < 1.0
        if not weak:
            for i in range(6):
                for j in range(6):
                    out_a[i, j] = icp_a[i, j] * icp_weight + rgbd_a[i, j] * rgbd_weight
                out_b[i] = icp_b[i] * icp_weight + rgbd_b[i] * rgbd_weight
            return
        weighted = scratch[5]  # V diag(max(kept, 0))
        for i in range(6):
            for k in range(6):
                weighted[i, k] = eigenvectors[i, k] * max(kept[k], 0.0)
        shrink = scratch[1]
        multiply_nt(weighted, eigenvectors, shrink, 6)
        multiply_tn(to_scaled, icp_a, scratch[5], 6)  # S^T A
        multiply(scratch[5], to_scaled, scratch[2], 6)  # S^T A S
        a_eta = scratch[5]
        multiply(shrink, scratch[2], a_eta, 6)
        b_scaled = rows[3]  # S^T b
        for i in range(6):
            total = 0.0
            for k in range(6):
                total += to_scaled[k, i] * icp_b[k]
            b_scaled[i] = total
        b_eta = rows[4]
        for i in range(6):
            total = 0.0
            for k in range(6):
                total += shrink[i, k] * b_scaled[k]
            b_eta[i] = total
        # from_scaled = (M D)^-1 = D^-1 M^-1 in closed form (for np.linalg.inv): D^-1 =
        # diag(lever x3, 1 x3) and M^-1 = [[I, 0], [-skew(c), I]] (a shear: its lower block
        # negated), so from_scaled = [[lever I, 0], [-skew(c), I]].
        from_scaled = scratch[3]
        for i in range(6):
            for j in range(6):
                from_scaled[i, j] = 0.0
        for i in range(3):
            from_scaled[i, i] = lever
            from_scaled[3 + i, 3 + i] = 1.0
        from_scaled[3, 1] = cz
        from_scaled[3, 2] = -cy
        from_scaled[4, 0] = -cz
        from_scaled[4, 2] = cx
        from_scaled[5, 0] = cy
        from_scaled[5, 1] = -cx
        symmetric = scratch[2]
        for i in range(6):
            for j in range(6):
                symmetric[i, j] = (a_eta[i, j] + a_eta[j, i]) / 2
        multiply_tn(from_scaled, symmetric, scratch[1], 6)
        a_world = scratch[0]
        multiply(scratch[1], from_scaled, a_world, 6)
        for i in range(6):
            total = 0.0
            for k in range(6):
                total += from_scaled[k, i] * b_eta[k]
            for j in range(6):
                out_a[i, j] = a_world[i, j] * icp_weight + rgbd_a[i, j] * rgbd_weight
            out_b[i] = total * icp_weight + rgbd_b[i] * rgbd_weight

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
                total = 0.0
                for k in range(3):
                    total += out[i, k] * right[k, j]
                left[i, j] = total / singular
        nearest = scratch[3]
        multiply_nt(left, right, nearest, 3)
        if determinant3(nearest) < 0:
            for i in range(3):
                left[i, 0] = -left[i, 0]
            multiply_nt(left, right, nearest, 3)
        for i in range(3):
            for j in range(3):
                out[i, j] = nearest[i, j]

    return SimpleNamespace(
        symmetric_eigen=symmetric_eigen,
        scaled_solution=scaled_solution,
        discounted_joint=discounted_joint,
        increment=increment,
        cholesky=cholesky,
    )
