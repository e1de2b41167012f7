"""The Gauss-Newton step's 6x6 algebra as device functions (kintinuous_fast.odometry.solve.ops)
against the host's compiled step (solve/__init__.py, odometry/combined.py: LAPACK) and the
reference's (NumPy), the ops compiled for the CPU with numba.njit (one lane: plain loops); then
the same ops compiled for CUDA in a one-thread kernel against the CPU compile, and the solve
kernel (odometry/frame_solve.py, the ops on a block of threads) against the reference's step (on
a GPU, or on numba's CUDA simulator in a child process: tests/conftest.py).

Tolerances, with the largest errors measured over these cases at 64 seeds in brackets:
- eigenvalues: 1e-12 x the largest |eigenvalue| of np.linalg.eigh's [1.4e-15]; eigenvectors
  orthonormal to 1e-13 [3.4e-15], A V = V diag(values) to 1e-12 x max |eigenvalue| [7.7e-16];
- increments of scaled_solution: rtol 1e-10, atol 1e-14 of the host's and the reference's (the
  bound of tests/test_fast_solve.py: a weak direction amplifies rounding by its condition)
  [2.4e-15 x max |xi|]; the condition number: 100 eps x itself [2.4 eps x itself];
- discounted_joint: 1e-12 x max |entry| of A and b (tests/test_fast_solve.py's) [A 5.7e-15,
  b 8.0e-15];
- increment: 1e-14 absolute of both apply_increments on poses near rotations [5.1e-15];
  reflections 3e-13 [1.2e-13], where the SVD is the less accurate
  (test_increment_of_a_reflection);
- the CUDA compile: bit for bit on the simulator (Python floats round as the CPU's loops), 1e-12
  x max |entry| on a GPU (fused multiply-adds).
- the solve kernel's new pose: 1e-12 absolute of the reference's step (its partial sums added
  in ranges, its eigenproblems in another order than LAPACK's).
"""

from pathlib import Path

import numba
import numpy as np
import pytest
from numba import cuda, float64  # a kernel's `cuda` must be a global: the simulator swaps it

from kintinuous_fast import cuda_is_simulated, cuda_status
from kintinuous_fast.odometry import combined as fast_combined
from kintinuous_fast.odometry import solve as fast
from kintinuous_fast.odometry.solve import (
    ILL_CONDITIONED,
    NOT_FINITE,
    SOLVED,
    UNCONSTRAINED,
    ops,
)
from kintinuous_fast.targets import cuda_device_jit
from kintinuous_ref import se3
from kintinuous_ref.odometry import combined as ref_combined
from kintinuous_ref.odometry import solve as ref
from kintinuous_ref.odometry.solve import MAX_CONDITION, LinearSystem

CPU = ops.build_ops(numba.njit(cache=True))
SEEDS = range(8)
ONE_LANE = (0, 1)  # the 6x6 steps' lane and lane count: plain loops


def scratch() -> np.ndarray:
    return np.full((ops.SCRATCH_MATRICES, 6, 6), np.nan)  # nothing may be read before written


def contiguous(system: LinearSystem) -> LinearSystem:
    """The system with A and b in arrays of their own (accumulate's are views of one product):
    one layout, so each op compiles once (closures are not cached: every process compiles)."""
    a, b = np.ascontiguousarray(system.A), np.ascontiguousarray(system.b)
    return LinearSystem(a, b, system.count, system.cost)


def random_system(seed: int, count: int = 400, weak_axis: int | None = None) -> LinearSystem:
    """tests/test_fast_solve.py's: `count` random rows, `weak_axis` scaled down by 1e-3."""
    rng = np.random.default_rng(seed)
    jacobian = rng.normal(size=(6, count))
    if weak_axis is not None:
        jacobian[weak_axis] *= 1e-3
    return contiguous(ref.accumulate(jacobian, rng.normal(scale=0.01, size=count)))


def corridor_system(seed: int, count: int = 600) -> LinearSystem:
    """Point-to-plane rows of a corridor: two walls (normals +-x) and a floor (+z) with normals
    tilted by ~1e-2, so the walking direction (y) is observed by a share ~1e-4 of the pairs.
    Row [p x n, n] (the world-frame left twist [omega, u]), residuals of a few millimetres."""
    rng = np.random.default_rng(seed)
    points = np.column_stack(
        [rng.uniform(-1, 1, count), rng.uniform(0, 6, count), rng.uniform(0, 2.5, count)]
    )
    normals = np.zeros((count, 3))
    side = rng.integers(0, 3, count)
    points[side == 0, 0], normals[side == 0, 0] = -1.0, 1.0
    points[side == 1, 0], normals[side == 1, 0] = 1.0, -1.0
    points[side == 2, 2], normals[side == 2, 2] = 0.0, 1.0
    normals += rng.normal(scale=1e-2, size=normals.shape)
    normals /= np.linalg.norm(normals, axis=1)[:, None]
    jacobian = np.hstack([np.cross(points, normals), normals]).T
    return contiguous(ref.accumulate(jacobian, rng.normal(scale=3e-3, size=count)))


def spectra(seed: int) -> list[np.ndarray]:
    """Symmetric 6x6 matrices: spread SPD, indefinite, repeated eigenvalues, diagonal, zero."""
    rng = np.random.default_rng(seed)
    q = np.linalg.qr(rng.normal(size=(6, 6)))[0]
    spread = q @ np.diag(10.0 ** rng.uniform(-8, 4, 6)) @ q.T
    m = rng.normal(size=(6, 6))
    repeated = q @ np.diag([1.0, 1.0, 1.0, 2.0, 2.0, 1e-9]) @ q.T
    matrices = [spread, m + m.T, repeated, np.diag(rng.normal(size=6)), np.zeros((6, 6))]
    matrices += [random_system(seed).A, corridor_system(seed).A]
    return [(a + a.T) / 2 for a in matrices]


@pytest.mark.parametrize("seed", SEEDS)
def test_symmetric_eigen_equals_eigh(seed: int) -> None:
    for a in spectra(seed):
        n = len(a)
        given = a.copy()
        values, vectors = np.full(n, np.nan), np.full((n, n), np.nan)
        CPU.symmetric_eigen(a, values, vectors, scratch(), *ONE_LANE)
        np.testing.assert_array_equal(a, given)  # `a` unchanged
        expected, expected_vectors = np.linalg.eigh(a)
        largest = max(np.abs(expected).max(), 1e-300)
        assert np.all(np.diff(values) >= 0)
        np.testing.assert_allclose(values, expected, rtol=0, atol=1e-12 * largest)
        np.testing.assert_allclose(vectors.T @ vectors, np.eye(n), rtol=0, atol=1e-13)
        np.testing.assert_allclose(a @ vectors, vectors * values, rtol=0, atol=1e-12 * largest)
        # where the eigenvalues are apart, the same vectors up to sign
        gaps = np.diff(expected) > 1e-6 * largest
        apart = np.concatenate([[True], gaps]) & np.concatenate([gaps, [True]])
        overlap = np.abs(vectors.T @ expected_vectors)[np.ix_(apart, apart)]
        np.testing.assert_allclose(overlap, np.eye(apart.sum()), rtol=0, atol=1e-8)


def eigen_from(ops_: object, a: np.ndarray, basis: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    values, vectors = np.full(6, np.nan), np.full((6, 6), np.nan)
    ops_.symmetric_eigen_from(a, basis, values, vectors, scratch(), *ONE_LANE)
    return values, vectors


@pytest.mark.parametrize("seed", SEEDS)
def test_symmetric_eigen_from_a_basis_equals_eigh(seed: int) -> None:
    """From any orthonormal basis the same eigenpairs (the tolerances above); from the identity
    symmetric_eigen's, bit for bit."""
    rotation = np.linalg.qr(np.random.default_rng(seed).normal(size=(6, 6)))[0]
    for a in spectra(seed):
        values, vectors = eigen_from(CPU, a, rotation)
        expected = np.linalg.eigh(a)[0]
        largest = max(np.abs(expected).max(), 1e-300)
        np.testing.assert_allclose(values, expected, rtol=0, atol=1e-12 * largest)
        np.testing.assert_allclose(vectors.T @ vectors, np.eye(6), rtol=0, atol=1e-13)
        np.testing.assert_allclose(a @ vectors, vectors * values, rtol=0, atol=1e-12 * largest)
        cold_values, cold_vectors = np.empty(6), np.empty((6, 6))
        CPU.symmetric_eigen(a, cold_values, cold_vectors, scratch(), *ONE_LANE)
        from_identity = eigen_from(CPU, a, np.eye(6))
        np.testing.assert_array_equal(from_identity[0], cold_values)
        np.testing.assert_array_equal(from_identity[1], cold_vectors)


@pytest.mark.parametrize("seed", SEEDS)
@pytest.mark.parametrize("kind", ["random", "corridor"])
def test_a_basis_near_the_eigenvectors_saves_sweeps(seed: int, kind: str) -> None:
    """The warm start's point: a Gauss-Newton step's information is close to the last step's,
    and from the last step's eigenvectors three sweeps give its eigenpairs to rounding, where
    from the identity they leave the eigenvectors 1e-9 to 1e-4 off (it needs 4-5 sweeps)."""
    three_sweeps = ops.build_ops(lambda function: function, max_sweeps=3)  # plain Python
    a = (random_system if kind == "random" else corridor_system)(seed).A
    a = (a + a.T) / 2
    change = np.random.default_rng(seed + 50).normal(size=(6, 6)) * 1e-3 * np.abs(a).max()
    nearby = a + (change + change.T) / 2
    expected = np.linalg.eigh(nearby)[0]
    largest = np.abs(expected).max()

    def residual(values: np.ndarray, vectors: np.ndarray) -> float:
        return np.abs(nearby @ vectors - vectors * values).max() / largest

    warm = eigen_from(three_sweeps, nearby, np.linalg.eigh(a)[1])
    np.testing.assert_allclose(warm[0], expected, rtol=0, atol=1e-12 * largest)
    assert residual(*warm) < 1e-12
    assert residual(*eigen_from(three_sweeps, nearby, np.eye(6))) > 1e-10


@pytest.mark.parametrize("seed", SEEDS)
@pytest.mark.parametrize("weak", [None, 0, 4])
def test_scaled_solution_equals_the_host(seed: int, weak: int | None) -> None:
    system = random_system(seed, weak_axis=weak)
    xi = np.full(6, np.nan)
    status, condition = CPU.scaled_solution(system.A, system.b, xi, scratch(), *ONE_LANE)
    host_status, host_xi, host_condition = fast._scaled_solution(system.A, system.b)
    assert (status, condition) == (host_status, host_condition) == (SOLVED, 0.0)
    np.testing.assert_allclose(xi, host_xi, rtol=1e-10, atol=1e-14)
    np.testing.assert_allclose(xi, ref.solve(system)[0], rtol=1e-10, atol=1e-14)


def test_scaled_solution_gives_the_host_statuses() -> None:
    """Each failure the host reports, in its order of checks, with xi left zero."""
    good = random_system(1)
    nan_a = good.A.copy()
    nan_a[2, 3] = np.nan
    inf_b = good.b.copy()
    inf_b[5] = np.inf
    unconstrained = good.A.copy()
    unconstrained[4, :] = unconstrained[:, 4] = 0.0
    unconstrained_nan = unconstrained.copy()
    unconstrained_nan[0, 0] = np.nan  # NOT_FINITE is checked first
    rows = np.random.default_rng(2).normal(size=(3, 6))
    plane = rows.T @ rows + np.eye(6) * 1e-30  # rank 3: one plane's point-to-plane rows
    # An indefinite matrix with a positive diagonal: its trace (the sum of its eigenvalues) is
    # positive, so eig_max > 0 > eig_min and the eigenvalue test reports it before Cholesky.
    indefinite = good.A.copy()
    indefinite[0, 1] = indefinite[1, 0] = 1e3 * np.sqrt(good.A[0, 0] * good.A[1, 1])
    cases = [
        (nan_a, good.b, NOT_FINITE),
        (good.A, inf_b, NOT_FINITE),
        (unconstrained_nan, good.b, NOT_FINITE),
        (unconstrained, good.b, UNCONSTRAINED),
        (plane, good.b, ILL_CONDITIONED),
        (indefinite, good.b, ILL_CONDITIONED),
    ]
    for a, b, expected in cases:
        xi = np.full(6, np.nan)
        status, condition = CPU.scaled_solution(a, b, xi, scratch(), *ONE_LANE)
        host_status, host_xi, host_condition = fast._scaled_solution(a, b)
        assert status == host_status == expected
        np.testing.assert_array_equal(xi, host_xi)
        np.testing.assert_array_equal(xi, np.zeros(6))
        if expected == ILL_CONDITIONED:
            assert condition > MAX_CONDITION and host_condition > MAX_CONDITION
        else:
            assert condition == host_condition == 0.0


def scaled_matrix(a: np.ndarray) -> np.ndarray:
    scale = 1.0 / np.sqrt(np.diag(a))
    return a * scale[:, None] * scale[None, :]


@pytest.mark.parametrize("seed", SEEDS)
def test_the_condition_bound_holds_and_is_the_inverse_trace(seed: int) -> None:
    """inverse_trace is trace(S^-1) from the Cholesky factor, and trace(S) trace(S^-1) bounds
    the condition number that the eigenvalue check measures (so a step below the bound may
    skip the eigenproblem)."""
    for a in (random_system(seed).A, random_system(seed, weak_axis=2).A, corridor_system(seed).A):
        s = scaled_matrix(a)
        factor, inverse = np.linalg.cholesky(s), np.empty((6, 6))
        trace = CPU.inverse_trace(factor, inverse, *ONE_LANE)
        np.testing.assert_allclose(trace, np.trace(np.linalg.inv(s)), rtol=1e-10)
        np.testing.assert_allclose(np.tril(inverse), np.linalg.inv(factor), rtol=1e-10, atol=1e-14)
        values = np.linalg.eigvalsh(s)
        assert values[-1] / values[0] <= np.trace(s) * trace


def test_a_condition_above_the_bound_goes_through_the_eigenvalues() -> None:
    """Systems whose bound is above CERTAIN_CONDITION, one solvable (condition 4e9) and one
    ill-conditioned (4e10): the eigenvalue check decides, as the host's, and the solvable one
    gets the host's increment."""
    q = np.linalg.qr(np.random.default_rng(3).normal(size=(6, 6)))[0]
    b = np.random.default_rng(4).normal(size=6)
    for condition, expected in ((4e9, SOLVED), (4e10, ILL_CONDITIONED)):
        a = q @ np.diag([1.0, 2.0, 3.0, 4.0, 5.0, 6.0 / condition]) @ q.T
        a = (a + a.T) / 2
        s = scaled_matrix(a)
        values = np.linalg.eigvalsh(s)
        assert np.trace(s) * np.trace(np.linalg.inv(s)) > ops.CERTAIN_CONDITION
        assert (values[-1] / values[0] > MAX_CONDITION) == (expected == ILL_CONDITIONED)
        xi = np.full(6, np.nan)
        status, measured = CPU.scaled_solution(a, b, xi, scratch(), *ONE_LANE)
        host_status, host_xi, host_condition = fast._scaled_solution(a, b)
        assert status == host_status == expected
        np.testing.assert_allclose(measured, host_condition, rtol=1e-3)
        np.testing.assert_allclose(xi, host_xi, rtol=1e-5, atol=1e-14 * np.abs(host_xi).max())


@pytest.mark.parametrize("seed", SEEDS)
def test_the_condition_number_equals_the_host(seed: int) -> None:
    """Beyond MAX_CONDITION by a known amount (about 1e11 and 1e12 after the Jacobi scaling):
    the host's condition to 100 eps x the condition, the bound that both eigensolvers' absolute
    error (~eps x the largest eigenvalue) in the smallest eigenvalue leaves."""
    rng = np.random.default_rng(seed)
    q = np.linalg.qr(rng.normal(size=(6, 6)))[0]
    for smallest in (1e-11, 1e-12):
        a = q @ np.diag([smallest, 0.5, 1.0, 1.5, 2.0, 3.0]) @ q.T
        a = (a + a.T) / 2
        status, condition = CPU.scaled_solution(a, np.ones(6), np.empty(6), scratch(), *ONE_LANE)
        host_status, _, host_condition = fast._scaled_solution(a, np.ones(6))
        assert status == host_status == ILL_CONDITIONED
        assert condition == pytest.approx(host_condition, rel=100 * 2.2e-16 * host_condition)


def test_cholesky_stops_at_a_pivot_that_is_not_positive() -> None:
    """NOT_DEFINITE: scaled_solution reaches Cholesky only with eig_min > eig_max / 1e10 > 0, a
    positive definite matrix whose condition (< 1e10) is far from where float64 Cholesky breaks
    down (~1 / (6 eps) ~ 1e15), so that status needs a non-finite pivot the eigen-test let
    through and no finite system gives it. The pivot test itself, directly:"""
    a = random_system(3).A
    lower = np.full((6, 6), np.nan)
    assert CPU.cholesky(a, 6, lower)
    np.testing.assert_allclose(lower, np.linalg.cholesky(a), rtol=1e-13, atol=0)
    indefinite = a.copy()
    indefinite[0, 1] = indefinite[1, 0] = 2 * np.sqrt(a[0, 0] * a[1, 1])
    assert not CPU.cholesky(indefinite, 6, np.empty((6, 6)))  # pivot 2 < 0
    singular = np.ones((6, 6))
    assert not CPU.cholesky(singular, 6, np.empty((6, 6)))  # pivot 2 == 0
    with_nan = a.copy()
    with_nan[3, 3] = np.nan
    assert not CPU.cholesky(with_nan, 6, np.empty((6, 6)))


def joint_arguments(icp: LinearSystem, rgbd: LinearSystem, centre: np.ndarray, threshold: float):
    """discounted_joint's inputs, its eigenproblem started from the identity."""
    return (icp.A, icp.b, icp.count, 1 / ref_combined.icp_scale(icp) ** 2, rgbd.A, rgbd.b, 0.3,
            *centre, threshold, np.eye(6))  # fmt: skip


@pytest.mark.parametrize("seed", SEEDS)
@pytest.mark.parametrize(
    "kind, threshold",
    [("random", 0.0), ("random", 0.02), ("random", 0.3), ("weak", 0.02), ("corridor", 0.02)],
)
def test_discounted_joint_equals_the_host(seed: int, kind: str, threshold: float) -> None:
    """Random systems with nothing, a weak direction or most directions discounted, and a
    corridor's point-to-plane system whose walking direction is discounted."""
    icp = {
        "random": random_system(seed),
        "weak": random_system(seed, weak_axis=(2, 5)[seed % 2]),
        "corridor": corridor_system(seed),
    }[kind]
    rgbd = random_system(seed + 100, count=150)
    centre = np.random.default_rng(seed).normal(size=3)
    out_a, out_b = np.full((6, 6), np.nan), np.full(6, np.nan)
    arguments = joint_arguments(icp, rgbd, centre, threshold)
    CPU.discounted_joint(*arguments, out_a, out_b, scratch(), *ONE_LANE)
    host_a, host_b = fast_combined._discounted_joint(*arguments[:7], centre, threshold)
    expected = ref_combined.joint_system(
        icp, rgbd, 0.3, "degeneracy-aware", 10.0, centre, threshold
    )
    for a, b in ((host_a, host_b), (expected.A, expected.b)):
        np.testing.assert_allclose(out_a, a, rtol=0, atol=1e-12 * np.abs(a).max())
        np.testing.assert_allclose(out_b, b, rtol=0, atol=1e-12 * np.abs(b).max())
    np.testing.assert_allclose(out_a, out_a.T, rtol=0, atol=1e-14 * np.abs(out_a).max())
    # the discount ran (or not) where the reference's spectrum says it does
    shares = ref_combined.information_spectrum(icp, centre)[0]
    plain = icp.A * arguments[3] + rgbd.A * 0.3
    discounted = threshold > 0 and shares.min() < threshold
    assert discounted or kind == "random"
    assert discounted != np.array_equal(out_a, plain)  # the sum itself where none is weak
    if kind == "corridor":
        assert shares.min() < 1e-2 * threshold  # the walking direction keeps under 1 %
    # the eigenvectors are left in the basis, and the next call starts from them
    basis, vectors = arguments[-1], ref_combined.information_spectrum(icp, centre)[1]
    np.testing.assert_allclose(basis.T @ basis, np.eye(6), rtol=0, atol=1e-13)
    np.testing.assert_allclose(np.abs(np.diag(basis.T @ vectors)), 1.0, rtol=0, atol=1e-8)
    warm_a, warm_b = np.full((6, 6), np.nan), np.full(6, np.nan)
    CPU.discounted_joint(*arguments, warm_a, warm_b, scratch(), *ONE_LANE)
    np.testing.assert_allclose(warm_a, host_a, rtol=0, atol=1e-12 * np.abs(host_a).max())
    np.testing.assert_allclose(warm_b, host_b, rtol=0, atol=1e-12 * np.abs(host_b).max())


def near_rotation(seed: int, drift: float = 1e-9) -> np.ndarray:
    """A pose whose rotation has drifted from orthonormal by about `drift`."""
    rng = np.random.default_rng(seed)
    pose = se3.exp(rng.normal(size=6))
    pose[:3, :3] += rng.normal(scale=drift, size=(3, 3))
    return pose


@pytest.mark.parametrize("seed", SEEDS)
@pytest.mark.parametrize("angle", [0.0, 1e-7, 5e-3, 0.05, 1.0, 3.0])
def test_increment_equals_apply_increment(seed: int, angle: float) -> None:
    """xi = 0 (translation 0 too at seed 0), both sides of the small-angle series (1e-2 rad) and
    large rotations, on poses whose rotation drifted from orthonormal (1e-9, 1e-6)."""
    rng = np.random.default_rng(seed)
    axis = rng.normal(size=3)
    xi = np.concatenate([angle * axis / np.linalg.norm(axis), (seed > 0) * rng.normal(size=3)])
    for drift in (1e-9, 1e-6):
        pose = near_rotation(seed, drift)
        out = np.full((4, 4), np.nan)
        CPU.increment(xi, pose, out, scratch())
        np.testing.assert_allclose(out, fast.apply_increment(xi, pose), rtol=0, atol=1e-14)
        np.testing.assert_allclose(out, ref.apply_increment(xi, pose), rtol=0, atol=1e-14)
        np.testing.assert_allclose(out[:3, :3] @ out[:3, :3].T, np.eye(3), rtol=0, atol=1e-14)
        np.testing.assert_array_equal(out[3], [0.0, 0.0, 0.0, 1.0])


@pytest.mark.parametrize("seed", SEEDS)
def test_increment_of_a_reflection(seed: int) -> None:
    """A rotation block with det < 0 (singular values 1.03, 1, 0.96 apart, so the smallest is
    well defined): the direction of the smallest singular value changes sign, as in the SVD.
    3e-13 of the SVD's: on these poses (64 seeds) LAPACK's own answer is up to 1.2e-13 from a
    40-digit SVD's (mpmath), the polar decomposition's within 4.1e-15; its defining property,
    Q^T R symmetric (R = Q V diag(-s_0, s_1, s_2) V^T), to 1e-14 [4.4e-16]."""
    rng = np.random.default_rng(seed)
    q = np.linalg.qr(rng.normal(size=(3, 3)))[0]
    w = np.linalg.qr(rng.normal(size=(3, 3)))[0]
    singular = rng.permutation([1.03, 1.0, 0.96])
    pose = np.eye(4)
    pose[:3, :3] = q @ np.diag(singular) @ w.T * np.sign(np.linalg.det(q @ w.T)) * -1
    pose[:3, 3] = rng.normal(size=3)
    assert np.linalg.det(pose[:3, :3]) < 0
    xi = rng.normal(scale=0.1, size=6)
    out = np.full((4, 4), np.nan)
    CPU.increment(xi, pose, out, scratch())
    np.testing.assert_allclose(out, fast.apply_increment(xi, pose), rtol=0, atol=3e-13)
    np.testing.assert_allclose(out, ref.apply_increment(xi, pose), rtol=0, atol=3e-13)
    assert np.linalg.det(out[:3, :3]) == pytest.approx(1.0, abs=1e-14)
    stretch = out[:3, :3].T @ (se3.exp(xi) @ pose)[:3, :3]
    np.testing.assert_allclose(stretch, stretch.T, rtol=0, atol=1e-14)


# ----------------------------------------------------------------------------------------------
# The same ops compiled for CUDA


@pytest.mark.skipif(cuda_status() == "", reason="CUDA works here: the kernel test runs directly")
@pytest.mark.cuda_simulator(Path(__file__), "-k", "one_thread_kernel or on_a_block")
def test_solve_ops_in_the_cuda_simulator(cuda_simulator) -> None:
    cuda_simulator()


@pytest.mark.skipif(bool(cuda_status()), reason="no CUDA GPU: runs in the simulator child")
def test_the_ops_in_a_one_thread_kernel() -> None:
    """symmetric_eigen, scaled_solution, discounted_joint and increment in one CUDA thread, its
    scratch a local array, on one corridor system: the CPU compile's results."""
    gpu = ops.build_ops(cuda_device_jit())
    symmetric_eigen, scaled_solution = gpu.symmetric_eigen, gpu.scaled_solution
    discounted_joint, increment = gpu.discounted_joint, gpu.increment
    k = ops.SCRATCH_MATRICES

    @cuda.jit
    def kernel(icp_a, icp_b, rgbd_a, rgbd_b, scalars, pose, basis, values, vectors, a, b, xi,
               status, out):  # fmt: skip
        scratch = cuda.local.array((k, 6, 6), float64)
        symmetric_eigen(icp_a, values, vectors, scratch, 0, 1)
        discounted_joint(icp_a, icp_b, 600, scalars[0], rgbd_a, rgbd_b, scalars[1], scalars[2],
                         scalars[3], scalars[4], scalars[5], basis, a, b, scratch, 0,
                         1)  # fmt: skip
        solved, condition = scaled_solution(a, b, xi, scratch, 0, 1)
        status[0] = solved
        status[1] = condition
        increment(xi, pose, out, scratch)

    icp = corridor_system(5)
    rgbd = random_system(105, count=150)
    centre = np.array([0.3, 2.0, 1.2])
    arguments = joint_arguments(icp, rgbd, centre, 0.02)
    scalars = np.array([arguments[3], 0.3, *centre, 0.02])
    pose = near_rotation(5, 1e-6)
    host = [np.zeros(6), np.zeros((6, 6)), np.zeros((6, 6)), np.zeros(6), np.zeros(6)]
    device = [cuda.to_device(x) for x in host]
    status, out = cuda.to_device(np.zeros(2)), cuda.to_device(np.zeros((4, 4)))
    inputs = [np.ascontiguousarray(x) for x in (icp.A, icp.b, rgbd.A, rgbd.b, scalars, pose)]
    inputs.append(np.eye(6))
    kernel[1, 1](*inputs, *device, status, out)
    values, vectors, a, b, xi = (x.copy_to_host() for x in device)

    expected_values, expected_vectors = np.empty(6), np.empty((6, 6))
    CPU.symmetric_eigen(icp.A, expected_values, expected_vectors, scratch(), *ONE_LANE)
    expected_a, expected_b = np.empty((6, 6)), np.empty(6)
    CPU.discounted_joint(*arguments, expected_a, expected_b, scratch(), *ONE_LANE)
    expected_xi = np.empty(6)
    expected_status = CPU.scaled_solution(expected_a, expected_b, expected_xi, scratch(), *ONE_LANE)
    expected_pose = np.empty((4, 4))
    CPU.increment(expected_xi, pose, expected_pose, scratch())

    assert tuple(status.copy_to_host()) == (SOLVED, 0.0) == expected_status
    pairs = [(values, expected_values), (a, expected_a), (b, expected_b), (xi, expected_xi)]
    pairs += [(out.copy_to_host(), expected_pose)]
    for got, expected in pairs:
        if cuda_is_simulated():  # Python floats round as the CPU's loops do
            np.testing.assert_array_equal(got, expected)
        else:  # fused multiply-adds on a GPU
            np.testing.assert_allclose(got, expected, rtol=0, atol=1e-12 * np.abs(expected).max())
    np.testing.assert_allclose(np.abs(vectors.T @ expected_vectors), np.eye(6), atol=1e-8)


# ----------------------------------------------------------------------------------------------
# The whole step on a CUDA block: odometry/frame_solve.py's kernel against the reference


def packed(system: LinearSystem) -> np.ndarray:
    """The NV summed values of a system (sums.unpack's layout)."""
    from kintinuous_fast.odometry.sums import NV, SLOT_B, SLOT_COST, SLOT_COUNT

    vector = np.zeros(NV)
    vector[:SLOT_B] = system.A[np.triu_indices(6)]
    vector[SLOT_B : SLOT_B + 6] = system.b
    vector[SLOT_COST], vector[SLOT_COUNT] = system.cost, system.count
    return vector


def block_partials(system: LinearSystem, blocks: int, seed: int) -> np.ndarray:
    """`blocks` random partial vectors that add up to the system's (as the kernels' blocks)."""
    shares = np.random.default_rng(seed).dirichlet(np.ones(blocks))
    return shares[:, None] * packed(system)[None, :]


def block_step(icp, rgbd, pose, mode, settings, blocks=37, level=1, failed=False, basis=None):  # noqa: ANN001, ANN201, E501
    """solve_kernel once on a block, from partials of `icp` and `rgbd` over `blocks` blocks
    (RGB-D's over 5 blocks), `pose` the estimate, `basis` (a device array; None: the identity)
    where the discount's eigenproblem starts: (state, poses) after it."""
    from kintinuous_fast.odometry import frame_kernels as slots
    from kintinuous_fast.odometry.frame_on_device import _initial_poses
    from kintinuous_fast.odometry.frame_solve import SOLVE_THREADS, solve_kernel

    state = np.zeros(slots.STATE_SIZE)
    state[slots.DONE_LEVEL], state[slots.MODE], state[slots.FAILED] = -1.0, mode, failed
    previous = se3.exp(np.array([0.01, -0.02, 0.03, 0.1, 0.0, -0.05]))
    poses = np.ascontiguousarray(_initial_poses(previous, None, pose))
    arrays = [cuda.to_device(x) for x in (np.zeros(2), state, poses)]
    icp_partials = cuda.to_device(block_partials(icp, blocks, 1))
    rgbd_partials = cuda.to_device(block_partials(rgbd, 5, 2))
    basis = cuda.to_device(np.eye(6)) if basis is None else basis
    solve_kernel[1, SOLVE_THREADS](icp_partials, rgbd_partials, *arrays, basis, settings, level)
    return arrays[1].copy_to_host(), arrays[2].copy_to_host(), previous


def assert_pose_step(poses: np.ndarray, previous: np.ndarray, expected: np.ndarray) -> None:
    """The new estimate and the relative poses the next kernels read."""
    np.testing.assert_allclose(poses[0], expected, rtol=0, atol=1e-12)
    np.testing.assert_array_equal(poses[3], poses[0])
    np.testing.assert_array_equal(poses[1], poses[0])  # no model pose: the identity
    np.testing.assert_allclose(poses[2], np.linalg.inv(previous) @ expected, rtol=0, atol=1e-12)


@pytest.mark.skipif(bool(cuda_status()), reason="no CUDA GPU: runs in the simulator child")
@pytest.mark.parametrize("blocks", [1, 37, 1024])
def test_the_joint_step_on_a_block(blocks: int) -> None:
    """The default weighting with a weak direction to discount (a corridor's ICP system), its
    partials over `blocks` blocks, so every range of the kernel's partial sums is used (and
    some are empty): the reference's joint system, solve and increment."""
    from kintinuous_fast.odometry import frame_kernels as slots

    icp, rgbd = corridor_system(7), random_system(107, count=150)
    pose = near_rotation(7, 1e-12)
    pose[:3, 3] = [0.4, 1.5, 1.1]
    settings = (10.0, 1e-12, slots.DISCOUNTED, 0.3, 10.0, 0.02)
    state, poses, previous = block_step(icp, rgbd, pose, slots.JOINT, settings, blocks)
    joint = ref_combined.joint_system(icp, rgbd, 0.3, "degeneracy-aware", 10.0, pose[:3, 3], 0.02)
    assert ref_combined.information_spectrum(icp, pose[:3, 3])[0].min() < 0.02  # discounted
    xi, reason = ref.solve(joint)
    assert reason == "" and state[slots.FAILED] == 0 and state[slots.DONE_LEVEL] == -1
    assert_pose_step(poses, previous, ref.apply_increment(xi, pose))
    # from another basis (as a later step starts) the same step, its eigenvectors left there
    basis = cuda.to_device(np.linalg.qr(np.random.default_rng(blocks).normal(size=(6, 6)))[0])
    _, poses, previous = block_step(icp, rgbd, pose, slots.JOINT, settings, blocks, basis=basis)
    assert_pose_step(poses, previous, ref.apply_increment(xi, pose))
    vectors = ref_combined.information_spectrum(icp, pose[:3, 3])[1]
    overlap = np.abs(basis.copy_to_host().T @ vectors)
    np.testing.assert_allclose(overlap, np.eye(6), rtol=0, atol=1e-8)


@pytest.mark.skipif(bool(cuda_status()), reason="no CUDA GPU: runs in the simulator child")
@pytest.mark.parametrize("weighting", ["information", "original-code"])
def test_the_joint_step_of_other_weightings_on_a_block(weighting: str) -> None:
    """The weightings that scale the two systems without the discount, each term by its own."""
    from kintinuous_fast.odometry import frame_kernels as slots

    icp, rgbd, pose = random_system(5), random_system(6, count=150), near_rotation(5, 1e-12)
    code = slots.WEIGHTING_CODES[weighting]
    state, poses, previous = block_step(
        icp, rgbd, pose, slots.JOINT, (10.0, 1e-12, code, 0.3, 10.0, 0.0)
    )
    joint = ref_combined.joint_system(icp, rgbd, 0.3, weighting, 10.0, pose[:3, 3], 0.0)
    assert state[slots.FAILED] == 0
    assert_pose_step(poses, previous, ref.apply_increment(ref.solve(joint)[0], pose))


@pytest.mark.skipif(bool(cuda_status()), reason="no CUDA GPU: runs in the simulator child")
def test_the_outcomes_of_a_step_on_a_block() -> None:
    """ICP alone (its own system), convergence, too few pairs, an ill-conditioned system and
    a closed gate, each as the reference's step ends."""
    from kintinuous_fast.odometry import frame_kernels as slots

    icp, rgbd, pose = random_system(3), random_system(4, count=150), near_rotation(3, 1e-12)
    plain = (10.0, 1e-12, slots.PAPER_METRES, 1.0, 1.0, 0.0)
    state, poses, previous = block_step(icp, rgbd, pose, slots.ICP_ONLY, plain)
    assert state[slots.FAILED] == 0 and state[slots.DONE_LEVEL] == -1
    assert_pose_step(poses, previous, ref.apply_increment(ref.solve(icp)[0], pose))

    converging = (10.0, 1.0, slots.PAPER_METRES, 1.0, 1.0, 0.0)  # every step is below 1
    state, _, _ = block_step(icp, rgbd, pose, slots.ICP_ONLY, converging, level=2)
    assert state[slots.FAILED] == 0 and state[slots.DONE_LEVEL] == 2

    too_many = (1e6, 1e-12, slots.PAPER_METRES, 1.0, 1.0, 0.0)
    state, poses, _ = block_step(icp, rgbd, pose, slots.JOINT, too_many)
    assert (state[slots.FAILED], state[slots.STATUS]) == (1.0, slots.TOO_FEW)
    assert state[slots.FAIL_COUNT] == icp.count + rgbd.count and state[slots.FAIL_LEVEL] == 1
    np.testing.assert_array_equal(poses[0], pose)

    rows = np.random.default_rng(2).normal(size=(3, 6))
    plane = LinearSystem(rows.T @ rows + np.eye(6) * 1e-30, np.ones(6), 400, 1.0)
    state, _, _ = block_step(plane, rgbd, pose, slots.ICP_ONLY, plain)
    assert (state[slots.FAILED], state[slots.STATUS]) == (1.0, ILL_CONDITIONED)
    assert state[slots.CONDITION] > MAX_CONDITION
    assert "singular system (condition number" in ref.solve(plane)[1]

    state, poses, _ = block_step(icp, rgbd, pose, slots.ICP_ONLY, plain, failed=True)
    assert state[slots.STATUS] == 0 and state[slots.DONE_LEVEL] == -1
    np.testing.assert_array_equal(poses[0], pose)
