"""The 6x6 algebra of a Gauss-Newton step, written once for the CPU and CUDA targets:
`build_ops(jit, barrier)` as in kintinuous_fast.targets. What solve/__init__.py and
odometry/combined.py compute on the host with LAPACK and fresh arrays (eigh, cholesky, svd, inv),
here without allocation, np.linalg or exceptions, so that a CUDA kernel can run the whole
iteration on the device: Jacobi's method for the symmetric eigenproblems, Cholesky and the two
triangular solves for the normal equations, the polar decomposition for the nearest rotation
(the one-lane pieces, the increment among them, are lane_ops.py's).

The 6x6 steps (symmetric_eigen, scaled_solution, discounted_joint) are written for a team of
`lanes` threads that all call them: lane e computes the elements e, e + lanes, ... of each
matrix (element k is row k // 6, column k % 6), and `barrier()` separates a step from the next
one that reads its results. On a CUDA block (odometry/frame_solve.py) the lanes are the
block's threads and the barrier is `cuda.syncthreads`; called with lane 0 of 1 and a barrier
that does nothing they are plain loops, which is how the CPU compile runs them, with the same
arithmetic in the same order. Work that is scalar (the checks, Cholesky) runs on lane 0, which
leaves its verdict in `scratch` for every lane to read after a barrier, so that every lane takes
the same branches and meets the same barriers. An element's sum runs over k ascending, as a
product does in matrices.product.

The eigenproblems use Jacobi's method in its parallel ordering (Golub and Van Loan, section
8.5): a sweep's 15 rotations go in 5 rounds of 3 whose index pairs are disjoint (the rounds of a
round-robin tournament of the 6 indices), and a round applies its 3 rotations at once, each
element of J^T A J from four elements of A. So 36 lanes take a sweep in 5 dependent steps
instead of 15. The 3x3 of the increment keeps the cyclic order on one lane.

Every intermediate lives in the caller's float64 `scratch` of shape (SCRATCH_MATRICES, 6, 6)
(on a CUDA block a shared array, for one thread a local one); vectors use rows of its matrices.
Which matrices each function uses is in its docstring; the arguments must not be views of them,
nor of each other.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from types import SimpleNamespace
from typing import Any

from kintinuous_ref.odometry.solve import MAX_CONDITION

from . import ILL_CONDITIONED, NOT_DEFINITE, NOT_FINITE, SOLVED, UNCONSTRAINED
from .lane_ops import MAX_SWEEPS, build_lane_ops

__all__ = ["SCRATCH_MATRICES", "build_ops"]

# The (6, 6) float64 matrices of a caller's scratch: the eigensolver's two iterates and the two
# of its eigenvectors (it reads one and writes the other each round), the rows of vectors and
# the lanes' shared verdict, then the steps' intermediates.
W0, W1, V0, V1, ROWS = range(5)
FREE = 5
SCRATCH_MATRICES = 10
VERDICT = 5  # scratch[ROWS, VERDICT, 0]: what lane 0 found, read by every lane
# scratch[ROWS]'s rows of a Jacobi round's rotations, per index: c, sigma and delta
ROTATION_C, ROTATION_SIGMA, ROTATION_DELTA = 2, 3, 4
ELEMENTS = 36
ROUNDS = 5  # a sweep of the 6x6 in the parallel ordering
# Below this bound on the scaled condition number the reference's check (MAX_CONDITION) cannot
# fail, with room for the eigenvalues' and the bound's rounding.
CERTAIN_CONDITION = MAX_CONDITION / 2


def build_ops(
    jit: Callable[[Any], Any], barrier: Any = None, max_sweeps: int = MAX_SWEEPS
) -> SimpleNamespace:
    """symmetric_eigen, scaled_solution, discounted_joint and increment (and the Cholesky
    factorisation they use) compiled with `jit`; `barrier` (a compiled function of no
    arguments) synchronises the lanes, None for one lane. `max_sweeps` caps the team's Jacobi
    sweeps (benchmarks time a sweep by capping it)."""
    one = build_lane_ops(jit)
    # Local names: numba resolves the functions a compiled function calls from its closure.
    product, product_tn, product_nt = one.product, one.product_tn, one.product_nt
    row_times, column_times = one.row_times, one.column_times
    jacobi_rotation, off_diagonal_negligible = one.jacobi_rotation, one.off_diagonal_negligible
    cholesky, increment = one.cholesky, one.increment
    forward_substitution, back_substitution = one.forward_substitution, one.back_substitution

    if barrier is None:

        @jit
        def barrier() -> None:
            """One lane: nothing to wait for."""

    @jit
    def partner(k: int, round_: int) -> int:
        """k's partner in round `round_` (0..4) of a round-robin tournament of 0..5 (the
        circle method: 5 stays, 0..4 turn): every pair meets once in the 5 rounds."""
        if k == 5:
            return round_
        if k == round_:
            return 5
        return (2 * round_ - k + 5) % 5

    @jit
    def pair_rotation(work: Any, k: int, round_: int) -> tuple[int, float, float, float]:
        """(m, c, sigma, delta) of index k in round `round_`: its partner m, and the rotation of
        the pair (p, q) = (min, max) as rotate applies it: column k of W J is c W[:, k] + sigma
        W[:, m] (sigma = -s for p, s for q), and W[k, k] gains delta (-t a_pq, t a_pq)."""
        m = partner(k, round_)
        p, q = min(k, m), max(k, m)
        apq = work[p, q]
        if apq == 0.0:
            return m, 1.0, 0.0, 0.0
        t, c, s = jacobi_rotation(work[p, p], work[q, q], apq)
        if k == p:
            return m, c, -s, -t * apq
        return m, c, s, t * apq

    @jit
    def round_rotations(work: Any, rows: Any, round_: int, lane: int, lanes: int) -> None:
        """Each index k's rotation in round `round_` (pair_rotation's c, sigma, delta) into
        rows[ROTATION_C:ROTATION_DELTA + 1, k], six lanes at once: computed once per index and
        read by every element's lane, which would otherwise compute two of them one after the
        other (a rotation's divisions and square roots are most of a round's time on a GPU)."""
        for k in range(lane, 6, lanes):
            _, c, sigma, delta = pair_rotation(work, k, round_)
            rows[ROTATION_C, k] = c
            rows[ROTATION_SIGMA, k] = sigma
            rows[ROTATION_DELTA, k] = delta

    @jit
    def round_entry(
        work: Any, vectors: Any, rows: Any, i: int, j: int, round_: int
    ) -> tuple[float, float]:
        """Element (i, j) of J^T W J and of V J after round `round_`'s three rotations, whose
        parameters round_rotations left in `rows`. An off-diagonal element is computed from its
        (min, max) end, so W stays exactly symmetric; a pair's own elements take rotate's forms
        (diagonal shifted, a_pq = 0)."""
        mi, mj = partner(i, round_), partner(j, round_)
        ci, si, di = rows[ROTATION_C, i], rows[ROTATION_SIGMA, i], rows[ROTATION_DELTA, i]
        cj, sj = rows[ROTATION_C, j], rows[ROTATION_SIGMA, j]
        vector = cj * vectors[i, j] + sj * vectors[i, mj]
        if i == j:
            return work[i, i] + di, vector
        if j == mi:
            return 0.0, vector
        if i > j:
            i, mi, ci, si, j, mj, cj, sj = j, mj, cj, sj, i, mi, ci, si
        row = cj * work[i, j] + sj * work[i, mj]
        partner_row = cj * work[mi, j] + sj * work[mi, mj]
        return ci * row + si * partner_row, vector

    @jit
    def diagonal_rank(work: Any, j: int) -> int:
        """Where W[j, j] goes in ascending order (ties by index)."""
        rank = 0
        for k in range(6):
            if work[k, k] < work[j, j] or (work[k, k] == work[j, j] and k < j):
                rank += 1
        return rank

    @jit
    def sweeps(values: Any, vectors: Any, scratch: Any, lane: int, lanes: int) -> None:
        """Jacobi's sweeps from the iterate scratch[W0] and the rotations so far scratch[V0]
        until the off-diagonal is negligible (or `max_sweeps`), then the diagonal ascending
        into `values` and the rotations' columns in the same order into `vectors`."""
        now = 0  # the iterates are scratch[W0 + now], scratch[V0 + now]
        for _ in range(max_sweeps):
            if off_diagonal_negligible(scratch[W0 + now], 6):  # every lane, the same answer
                break
            for round_ in range(ROUNDS):
                round_rotations(scratch[W0 + now], scratch[ROWS], round_, lane, lanes)
                barrier()
                for e in range(lane, ELEMENTS, lanes):
                    i, j = e // 6, e % 6
                    w, v = round_entry(
                        scratch[W0 + now], scratch[V0 + now], scratch[ROWS], i, j, round_
                    )
                    scratch[W1 - now, i, j] = w
                    scratch[V1 - now, i, j] = v
                barrier()
                now = 1 - now
        for e in range(lane, ELEMENTS, lanes):
            i, j = e // 6, e % 6
            rank = diagonal_rank(scratch[W0 + now], j)
            if i == 0:
                values[rank] = scratch[W0 + now, j, j]
            vectors[i, rank] = scratch[V0 + now, i, j]
        barrier()

    @jit
    def symmetric_eigen(
        a: Any, values: Any, vectors: Any, scratch: Any, lane: int, lanes: int
    ) -> None:
        """np.linalg.eigh of the symmetric 6x6 `a` (unchanged): eigenvalues ascending into
        `values` (6,), unit eigenvectors as the columns of `vectors` (6, 6), by Jacobi in the
        parallel ordering. Uses scratch[W0:V1 + 1] and rows ROTATION_C..ROTATION_DELTA of
        scratch[ROWS], which its callers fill only after it."""
        for e in range(lane, ELEMENTS, lanes):
            i, j = e // 6, e % 6
            scratch[W0, i, j] = a[i, j]
            scratch[V0, i, j] = 1.0 if i == j else 0.0
        barrier()
        sweeps(values, vectors, scratch, lane, lanes)

    @jit
    def symmetric_eigen_from(
        a: Any, basis: Any, values: Any, vectors: Any, scratch: Any, lane: int, lanes: int
    ) -> None:
        """symmetric_eigen started from `basis` (6, 6), orthonormal columns: Jacobi rotates
        B^T a B and accumulates its rotations on B. Where B holds the eigenvectors of a matrix
        near `a` (the last Gauss-Newton step's), B^T a B is nearly diagonal and Jacobi, which
        converges quadratically, needs fewer sweeps. With B = I every sum is exact and the
        result is symmetric_eigen's, bit for bit. Uses what symmetric_eigen uses."""
        for e in range(lane, ELEMENTS, lanes):  # B^T a
            i, j = e // 6, e % 6
            scratch[W1, i, j] = product_tn(basis, a, i, j, 6)
        barrier()
        for e in range(lane, ELEMENTS, lanes):  # B^T a B
            i, j = e // 6, e % 6
            scratch[V1, i, j] = product(scratch[W1], basis, i, j, 6)
        barrier()
        for e in range(lane, ELEMENTS, lanes):  # its symmetric part; the rotations start at B
            i, j = e // 6, e % 6
            scratch[W0, i, j] = (scratch[V1, i, j] + scratch[V1, j, i]) / 2
            scratch[V0, i, j] = basis[i, j]
        barrier()
        sweeps(values, vectors, scratch, lane, lanes)

    @jit
    def system_status(A: Any, b: Any) -> int:
        """NOT_FINITE, UNCONSTRAINED or SOLVED: the host's checks before the eigenvalues."""
        for i in range(6):
            for j in range(6):
                if not math.isfinite(A[i, j]):
                    return NOT_FINITE
            if not math.isfinite(b[i]):
                return NOT_FINITE
        for i in range(6):
            if A[i, i] <= 0:
                return UNCONSTRAINED
        return SOLVED

    @jit
    def factored_solution(scale: Any, b: Any, xi: Any, factor: Any, rows: Any) -> None:
        """xi = D^-1/2 y with (D^-1/2 A D^-1/2) y = -D^-1/2 b, `factor` its Cholesky factor L
        (L L^T = D^-1/2 A D^-1/2) and `scale` = D^-1/2; on one lane. Uses rows[2:4]."""
        rhs = rows[2]
        for i in range(6):
            rhs[i] = -b[i] * scale[i]
        forward_substitution(factor, rhs, rows[3], 6)
        back_substitution(factor, rows[3], rhs, 6)
        for i in range(6):
            xi[i] = rhs[i] * scale[i]

    @jit
    def inverse_trace(factor: Any, inverse: Any, lane: int, lanes: int) -> float:
        """trace((L L^T)^-1) of a Cholesky factor L: the squares of L^-1's entries added. Lane
        k < 6 solves for column k of L^-1 into `inverse`; every lane then adds the same squares
        in the same order, so every lane returns the same value."""
        for k in range(lane, 6, lanes):
            for i in range(6):
                total = 0.0
                if i >= k:
                    total = 1.0 if i == k else 0.0
                    for j in range(k, i):
                        total -= factor[i, j] * inverse[j, k]
                    total /= factor[i, i]
                inverse[i, k] = total
        barrier()
        trace = 0.0
        for i in range(6):
            for k in range(i + 1):
                trace += inverse[i, k] * inverse[i, k]
        return trace

    @jit
    def lane_verdict(scratch: Any, lane: int, value: float) -> float:
        """Lane 0's `value`, returned to every lane (read after a barrier)."""
        if lane == 0:
            scratch[ROWS, VERDICT, 0] = value
        barrier()
        verdict = scratch[ROWS, VERDICT, 0]
        barrier()  # every lane has read it before lane 0 may write the next
        return verdict

    @jit
    def scaled_solution(
        A: Any, b: Any, xi: Any, scratch: Any, lane: int, lanes: int
    ) -> tuple[int, float]:
        """(status, condition) of the normal equations A xi = -b (eq. 12-13), xi (6,) written
        (zeros unless SOLVED): solve/__init__.py's _scaled_solution, the same statuses. That
        one checks the condition of the Jacobi-scaled matrix S = D^-1/2 A D^-1/2 by its
        eigenvalues, then factors S by Cholesky. Here Cholesky goes first, and where it
        succeeds, trace(S) trace(S^-1) bounds the condition from above (lambda_max <= trace(S),
        1 / lambda_min <= trace(S^-1)): below CERTAIN_CONDITION the eigenvalue check cannot
        fail, and the eigenproblem (most of a step's time on a GPU) is skipped. Otherwise the
        check runs as there. Uses scratch[:FREE + 4]: FREE the scaled matrix, FREE + 1 its
        eigenvectors, FREE + 2 the Cholesky factor, FREE + 3 its inverse, ROWS's rows the
        scale, the eigenvalues and the two triangular solves."""
        status = SOLVED
        if lane == 0:
            for i in range(6):
                xi[i] = 0.0
            status = system_status(A, b)
        status = int(lane_verdict(scratch, lane, status))
        if status != SOLVED:
            return status, 0.0
        scaled, factor = scratch[FREE], scratch[FREE + 2]
        rows = scratch[ROWS]
        scale = rows[0]
        for i in range(lane, 6, lanes):
            scale[i] = 1.0 / math.sqrt(A[i, i])
        barrier()
        for e in range(lane, ELEMENTS, lanes):
            i, j = e // 6, e % 6
            scaled[i, j] = A[i, j] * scale[i] * scale[j]
        barrier()
        factored = False
        if lane == 0:
            factored = cholesky(scaled, 6, factor)
        factored = lane_verdict(scratch, lane, factored) != 0.0
        if factored:
            trace = 0.0
            for i in range(6):
                trace += scaled[i, i]
            bound = trace * inverse_trace(factor, scratch[FREE + 3], lane, lanes)
            if bound < CERTAIN_CONDITION:
                if lane == 0:
                    factored_solution(scale, b, xi, factor, rows)
                barrier()
                return SOLVED, 0.0
        eigenvalues = rows[1]
        symmetric_eigen(scaled, eigenvalues, scratch[FREE + 1], scratch, lane, lanes)
        if eigenvalues[0] <= eigenvalues[5] / MAX_CONDITION:
            return ILL_CONDITIONED, eigenvalues[5] / max(eigenvalues[0], 1e-300)
        if not factored:
            return NOT_DEFINITE, 0.0
        if lane == 0:
            factored_solution(scale, b, xi, factor, rows)
        barrier()
        return SOLVED, 0.0

    @jit
    def change_entry(i: int, j: int, cx: float, cy: float, cz: float) -> float:
        """M[i, j], M = [[I, 0], [skew(c), I]] (combined.about_camera)."""
        if i == j:
            return 1.0
        if i == 3 and j == 1:
            return -cz
        if i == 3 and j == 2:
            return cy
        if i == 4 and j == 0:
            return cz
        if i == 4 and j == 2:
            return -cx
        if i == 5 and j == 0:
            return -cy
        if i == 5 and j == 1:
            return cx
        return 0.0

    @jit
    def from_scaled_entry(i: int, j: int, lever: float, cx: float, cy: float, cz: float) -> float:
        """((M D)^-1)[i, j] in closed form (for np.linalg.inv): D^-1 = diag(lever x3, 1 x3)
        and M^-1 = [[I, 0], [-skew(c), I]] (a shear: its lower block negated), so (M D)^-1 =
        [[lever I, 0], [-skew(c), I]]."""
        if i == j:
            return lever if i < 3 else 1.0
        entry = change_entry(i, j, cx, cy, cz)
        return -entry if entry != 0.0 else 0.0

    @jit
    def lever_scale(i: int, lever: float) -> float:
        """D[i, i], D = diag(1 / lever x3, 1 x3)."""
        return 1 / lever if i < 3 else 1.0

    @jit
    def kept_share(value: float, threshold: float) -> float:
        """How much of an information direction the discount keeps (1 with no threshold)."""
        return min(value / threshold, 1.0) if threshold > 0 else 1.0

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
        basis: Any,
        out_a: Any,
        out_b: Any,
        scratch: Any,
        lane: int,
        lanes: int,
    ) -> None:
        """(out_a, out_b) = combined.py's _discounted_joint (the joint normal equations of
        eq. 12-13, "degeneracy-aware"): the ICP system with its weak directions discounted, its
        information measured about the centre (cx, cy, cz), times `icp_weight`, plus the RGB-D
        system times `rgbd_weight`. The information's eigenproblem starts from `basis` (6, 6),
        orthonormal columns (the identity, or the eigenvectors the last call left there:
        symmetric_eigen_from), and leaves its eigenvectors there. Uses all of scratch."""
        f0, f1, f2, f3, f4 = FREE, FREE + 1, FREE + 2, FREE + 3, FREE + 4
        rows = scratch[ROWS]
        for e in range(lane, ELEMENTS, lanes):  # M
            i, j = e // 6, e % 6
            scratch[f0, i, j] = change_entry(i, j, cx, cy, cz)
        barrier()
        for e in range(lane, ELEMENTS, lanes):  # M^T A
            i, j = e // 6, e % 6
            scratch[f1, i, j] = product_tn(scratch[f0], icp_a, i, j, 6)
        barrier()
        for e in range(lane, ELEMENTS, lanes):  # C = M^T A M
            i, j = e // 6, e % 6
            scratch[f2, i, j] = product(scratch[f1], scratch[f0], i, j, 6)
        barrier()
        centred = scratch[f2]
        translational = max(centred[3, 3] + centred[4, 4] + centred[5, 5], 1e-300)
        rotational = max(centred[0, 0] + centred[1, 1] + centred[2, 2], 1e-300)
        lever = math.sqrt(rotational / translational)
        for e in range(lane, ELEMENTS, lanes):  # information D C D / count, S = M D
            i, j = e // 6, e % 6
            scale_i, scale_j = lever_scale(i, lever), lever_scale(j, lever)
            scratch[f1, i, j] = scale_i * centred[i, j] * scale_j / max(icp_count, 1)
            scratch[f3, i, j] = scratch[f0, i, j] * scale_j
        barrier()
        eigenvalues, eigenvectors = rows[1], scratch[f2]
        symmetric_eigen_from(scratch[f1], basis, eigenvalues, eigenvectors, scratch, lane, lanes)
        for e in range(lane, ELEMENTS, lanes):  # no lane reads `basis` again in this call
            i, j = e // 6, e % 6
            basis[i, j] = eigenvectors[i, j]
        weak = False
        for k in range(6):
            weak = weak or kept_share(eigenvalues[k], threshold) < 1.0
        if not weak:
            for e in range(lane, ELEMENTS, lanes):
                i, j = e // 6, e % 6
                out_a[i, j] = icp_a[i, j] * icp_weight + rgbd_a[i, j] * rgbd_weight
                if j == 0:
                    out_b[i] = icp_b[i] * icp_weight + rgbd_b[i] * rgbd_weight
            barrier()
            return
        for e in range(lane, ELEMENTS, lanes):  # V diag(max(kept, 0))
            i, k = e // 6, e % 6
            scratch[f0, i, k] = eigenvectors[i, k] * max(kept_share(eigenvalues[k], threshold), 0.0)
        barrier()
        b_scaled, b_eta = rows[3], rows[4]
        for e in range(lane, ELEMENTS, lanes):  # shrink = V diag V^T; S^T A; S^T b
            i, j = e // 6, e % 6
            scratch[f1, i, j] = product_nt(scratch[f0], eigenvectors, i, j, 6)
            scratch[f4, i, j] = product_tn(scratch[f3], icp_a, i, j, 6)
            if j == 0:
                b_scaled[i] = column_times(scratch[f3], icp_b, i, 6)
        barrier()
        for e in range(lane, ELEMENTS, lanes):  # S^T A S; shrink S^T b
            i, j = e // 6, e % 6
            scratch[f0, i, j] = product(scratch[f4], scratch[f3], i, j, 6)
            if j == 0:
                b_eta[i] = row_times(scratch[f1], b_scaled, i, 6)
        barrier()
        for e in range(lane, ELEMENTS, lanes):  # shrink S^T A S
            i, j = e // 6, e % 6
            scratch[f2, i, j] = product(scratch[f1], scratch[f0], i, j, 6)
        barrier()
        for e in range(lane, ELEMENTS, lanes):  # its symmetric part; (M D)^-1
            i, j = e // 6, e % 6
            scratch[f3, i, j] = (scratch[f2, i, j] + scratch[f2, j, i]) / 2
            scratch[f4, i, j] = from_scaled_entry(i, j, lever, cx, cy, cz)
        barrier()
        for e in range(lane, ELEMENTS, lanes):
            i, j = e // 6, e % 6
            scratch[f0, i, j] = product_tn(scratch[f4], scratch[f3], i, j, 6)
        barrier()
        for e in range(lane, ELEMENTS, lanes):  # back in the world frame, weighted, + RGB-D
            i, j = e // 6, e % 6
            a_world = product(scratch[f0], scratch[f4], i, j, 6)
            out_a[i, j] = a_world * icp_weight + rgbd_a[i, j] * rgbd_weight
            if j == 0:
                world_b = column_times(scratch[f4], b_eta, i, 6)
                out_b[i] = world_b * icp_weight + rgbd_b[i] * rgbd_weight
        barrier()

    return SimpleNamespace(
        symmetric_eigen=symmetric_eigen,
        symmetric_eigen_from=symmetric_eigen_from,
        scaled_solution=scaled_solution,
        discounted_joint=discounted_joint,
        increment=increment,
        cholesky=cholesky,
        inverse_trace=inverse_trace,
    )
