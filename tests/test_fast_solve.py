"""The compiled Gauss-Newton step (kintinuous_fast.odometry.solve) against the reference's
(kintinuous_ref.odometry.solve and combined): the same increments, poses and joint systems to
rounding on random systems, the same reasons on every kind of system that has no solution, and
refine's answer on a problem whose minimum is known."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from kintinuous_fast.odometry import combined as fast_combined
from kintinuous_fast.odometry import cpu
from kintinuous_fast.odometry import solve as fast
from kintinuous_ref import se3
from kintinuous_ref.config import Config
from kintinuous_ref.odometry import combined as ref_combined
from kintinuous_ref.odometry import solve as ref
from kintinuous_ref.odometry.solve import LinearSystem

seeds = st.integers(0, 2**32 - 1)


def random_system(seed: int, count: int = 400, weak_axis: int | None = None) -> LinearSystem:
    """Normal equations of `count` random rows; `weak_axis` scaled down by 1e-3 (a direction
    few rows observe)."""
    rng = np.random.default_rng(seed)
    jacobian = rng.normal(size=(6, count))
    if weak_axis is not None:
        jacobian[weak_axis] *= 1e-3
    residuals = rng.normal(scale=0.01, size=count)
    return ref.accumulate(jacobian, residuals)


@settings(max_examples=60, deadline=None)
@given(seed=seeds, weak=st.sampled_from([None, 0, 4]))
def test_solve_equals_the_reference(seed: int, weak: int | None) -> None:
    system = random_system(seed, weak_axis=weak)
    expected, expected_reason = ref.solve(system)
    got, reason = fast.solve(system)
    assert reason == expected_reason == ""
    np.testing.assert_allclose(got, expected, rtol=1e-10, atol=1e-14)


def test_solve_gives_the_reference_reasons() -> None:
    good = random_system(1)
    nan_a = good.A.copy()
    nan_a[2, 3] = np.nan
    unconstrained = good.A.copy()
    unconstrained[4, :] = unconstrained[:, 4] = 0.0
    plane = np.zeros((6, 6))  # rank 3: one plane's point-to-plane rows
    normal_rows = np.random.default_rng(2).normal(size=(3, 6))
    plane += normal_rows.T @ normal_rows
    plane += np.eye(6) * 1e-30
    indefinite = good.A.copy()
    indefinite[0, 1] = indefinite[1, 0] = 1e3 * np.sqrt(good.A[0, 0] * good.A[1, 1])
    cases = {
        "too few": (LinearSystem(good.A, good.b, 3, 0.0), "too few correspondences (3 < 6)"),
        "nan": (LinearSystem(nan_a, good.b, 400, 0.0), "NaN"),
        "unconstrained": (LinearSystem(unconstrained, good.b, 400, 0.0), "no constraint"),
        "plane": (LinearSystem(plane, good.b, 400, 0.0), "condition number"),
        "indefinite": (LinearSystem(indefinite, good.b, 400, 0.0), "singular"),
    }
    pose = se3.exp(np.array([0.1, -0.2, 0.3, 1.0, 2.0, 3.0]))
    for name, (system, words) in cases.items():
        expected = ref.solve(system)
        got = fast.solve(system)
        assert got[0] is None and expected[0] is None, name
        assert got[1] == expected[1], name
        assert words in got[1], name
        # the same step in compiled code (a level's compiled loop): the pose left as it was
        step = fast.gauss_newton_step(system.A, system.b, system.count, 6, pose)
        status, condition, kept, _ = step
        assert fast.failure_reason(status, condition, system.count, 6) == expected[1], name
        np.testing.assert_array_equal(kept, pose)


@settings(max_examples=30, deadline=None)
@given(seed=seeds, weak=st.sampled_from([None, 0, 4]))
def test_a_compiled_step_is_solve_then_apply_increment(seed: int, weak: int | None) -> None:
    """gauss_newton_step, the step of a level's compiled loop, against the reference's solve and
    apply_increment: the new pose to rounding, and the step's length as np.linalg.norm's."""
    system = random_system(seed, weak_axis=weak)
    pose = se3.exp(np.random.default_rng(seed).normal(size=6))
    xi, _ = ref.solve(system)
    status, _, updated, length = fast.gauss_newton_step(system.A, system.b, system.count, 6, pose)
    assert status == fast.SOLVED
    np.testing.assert_allclose(updated, ref.apply_increment(xi, pose), rtol=0, atol=1e-12)
    assert length == pytest.approx(float(np.linalg.norm(xi)), rel=1e-10)


@settings(max_examples=60, deadline=None)
@given(
    seed=seeds,
    angle=st.sampled_from([0.0, 1e-7, 5e-3, 0.05, 1.0, 3.0]),
    translation=st.floats(0.0, 2.0),
)
def test_apply_increment_equals_the_reference(seed: int, angle: float, translation: float) -> None:
    """Both sides of the small-angle series (1e-2 rad) and large rotations."""
    rng = np.random.default_rng(seed)
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    xi = np.concatenate([angle * axis, translation * rng.normal(size=3)])
    pose = se3.exp(rng.normal(size=6))
    got = fast.apply_increment(xi, pose)
    np.testing.assert_allclose(got, ref.apply_increment(xi, pose), rtol=0, atol=1e-13)
    np.testing.assert_allclose(got[:3, :3] @ got[:3, :3].T, np.eye(3), atol=1e-14)
    assert np.linalg.det(got[:3, :3]) == pytest.approx(1.0, abs=1e-14)


@settings(max_examples=40, deadline=None)
@given(
    seed=seeds,
    weighting=st.sampled_from(ref_combined.WEIGHTINGS),
    threshold=st.sampled_from([0.0, 0.02, 0.3]),
    weak=st.sampled_from([None, 2, 5]),
)
def test_joint_system_equals_the_reference(
    seed: int, weighting: str, threshold: float, weak: int | None
) -> None:
    """Every weighting; the degeneracy-aware ones with no direction discounted (threshold 0),
    a weak one discounted (0.02) and most discounted (0.3)."""
    icp = random_system(seed, weak_axis=weak)
    rgbd = random_system(seed + 1, count=150)
    centre = np.random.default_rng(seed).normal(size=3)
    arguments = (0.3, weighting, 10.0, centre, threshold)
    expected = ref_combined.joint_system(icp, rgbd, *arguments)
    got = fast_combined.joint_system(icp, rgbd, *arguments)
    scale = np.abs(expected.A).max()
    np.testing.assert_allclose(got.A, expected.A, rtol=0, atol=1e-12 * scale)
    np.testing.assert_allclose(got.b, expected.b, rtol=0, atol=1e-12 * np.abs(expected.b).max())
    assert got.count == expected.count
    assert got.cost == pytest.approx(expected.cost, rel=1e-14)


def test_refine_reaches_a_known_pose() -> None:
    """Point-to-point alignment of points moved by a known motion: the system at a pose is the
    linearised error of the moved points, so refine lands on the motion itself."""
    rng = np.random.default_rng(7)
    points = rng.uniform(-1, 1, size=(200, 3))
    truth = se3.exp(np.array([0.05, -0.03, 0.02, 0.1, 0.05, -0.08]))
    targets = points @ truth[:3, :3].T + truth[:3, 3]

    def system_at(level: int, pose: np.ndarray) -> LinearSystem:
        moved = points @ pose[:3, :3].T + pose[:3, 3]
        rows = []
        for axis in range(3):  # d(moved)/d(omega, u) = [-[p]x | I], one row per axis
            unit = np.eye(3)[axis]
            rows.append(np.hstack([np.cross(moved, unit), np.tile(unit, (len(points), 1))]))
        jacobian = np.concatenate(rows).T
        residuals = (moved - targets).T.reshape(-1)
        return ref.accumulate(jacobian, residuals)

    pose, reason = fast.refine(np.eye(4), system_at, (10, 10), 6, 1e-12)
    assert reason == ""
    np.testing.assert_allclose(pose, truth, atol=1e-12)
    expected, _ = ref.refine(np.eye(4), system_at, (10, 10), 6, 1e-12)
    np.testing.assert_allclose(pose, expected, atol=1e-14)
    # `step` as the reference's: the reference's own step gives the reference's pose.
    stepped, _ = fast.refine(
        np.eye(4), system_at, (10, 10), 6, 1e-12, (ref.solve, ref.apply_increment)
    )
    np.testing.assert_array_equal(stepped, expected)


def test_the_cpu_backend_tracks_with_the_compiled_step() -> None:
    tracker = cpu.make_tracker("icp+rgbd", Config(), None)
    assert tracker.systems.refine is fast.refine
    assert tracker.systems.CombinedProblem is fast_combined.CombinedProblem
