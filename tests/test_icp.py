"""ICP (paper eq. 6-10) against independent truths: an analytic room with known poses, finite
differences of the point-to-plane cost, hand-built pairs for the rejection tests."""

from __future__ import annotations

import dataclasses

import numpy as np
import odometry_scene as scene
import pytest

from kintinuous_ref.camera import Intrinsics
from kintinuous_ref.odometry.icp import (
    IcpProblem,
    associate,
    icp_system,
    pair_weights,
    point_to_plane_cost,
    point_to_plane_rows,
    robust_threshold,
    robust_weights,
    valid_points,
)
from kintinuous_ref.odometry.solve import LinearSystem, accumulate, refine, solve


@pytest.fixture(scope="module")
def room_pair():
    previous, current = scene.room_poses()
    return previous, current, scene.frame(current, levels=3), scene.model(previous)


def test_known_motion_is_recovered(room_pair):
    previous, current, frame, model = room_pair
    problem = IcpProblem(frame.levels, model, previous)
    estimate, reason = refine(previous.copy(), problem.system, (10, 5, 4))
    assert reason == ""
    translation_mm, rotation_deg = scene.pose_error(estimate, current)
    # Noise-free exact geometry: the brief's 1 mm / 0.1 degree, with a wide margin in practice.
    assert translation_mm < 1.0
    assert rotation_deg < 0.1
    # Nearly every valid pixel finds its model point once aligned.
    assert problem.inlier_fraction(estimate) > 0.9


def test_jacobian_matches_finite_differences():
    rng = np.random.default_rng(1)
    world = rng.uniform(-2, 2, (3, 50)) + np.array([[0.5], [1.0], [3.0]])
    model_vertices = world + rng.normal(0, 0.02, (3, 50))
    normals = rng.normal(size=(3, 50))
    normals /= np.linalg.norm(normals, axis=0)
    jacobian, residuals = point_to_plane_rows(world, model_vertices, normals)
    np.testing.assert_allclose(
        residuals, point_to_plane_cost(np.zeros(6), world, model_vertices, normals)
    )
    step = 1e-6
    for k in range(6):
        xi = np.zeros(6)
        xi[k] = step
        numeric = (
            point_to_plane_cost(xi, world, model_vertices, normals)
            - point_to_plane_cost(-xi, world, model_vertices, normals)
        ) / (2 * step)
        # Central differences: error O(step^2 * second derivative) ~ 1e-11; rounding ~ 1e-10.
        np.testing.assert_allclose(jacobian[k], numeric, atol=1e-7)


def test_normal_equations_are_double_precision_sums():
    rng = np.random.default_rng(2)
    jacobian = rng.normal(size=(6, 1000)).astype(np.float32)
    residuals = rng.normal(size=1000).astype(np.float32)
    system = accumulate(jacobian, residuals)
    j64, r64 = jacobian.astype(np.float64), residuals.astype(np.float64)
    assert system.A.dtype == np.float64
    np.testing.assert_allclose(system.A, j64 @ j64.T, rtol=1e-12)
    np.testing.assert_allclose(system.b, j64 @ r64, rtol=1e-12)
    assert system.cost == pytest.approx(float(r64 @ r64), rel=1e-12)


def test_a_level_ends_at_its_first_step_shorter_than_converged():
    # Steps of 1 cm shrinking 0.3x each (the geometric tail of a converging Gauss-Newton): the
    # first under 10 um is the 7th, 0.01 * 0.3**6 = 7.3 um, so the level stops after 7 of its
    # 10 iterations; with a threshold of 0 it runs all 10.
    def shrinking_steps(steps: list[float]):  # noqa: ANN202
        def system_at(level: int, pose: np.ndarray) -> LinearSystem:
            steps.append(0.01 * 0.3 ** len(steps))
            return LinearSystem(np.eye(6), np.array([0, 0, 0, -steps[-1], 0, 0]), 100, 0.0)

        return system_at

    for converged, expected in ((1e-5, 7), (0.0, 10)):
        steps: list[float] = []
        pose, reason = refine(np.eye(4), shrinking_steps(steps), (10,), converged=converged)
        assert reason == "" and len(steps) == expected
        # translations along x add up exactly: the sum of the steps taken
        assert pose[0, 3] == pytest.approx(sum(steps), rel=1e-12)


def test_solve_is_the_least_squares_step():
    rng = np.random.default_rng(3)
    jacobian = rng.normal(size=(6, 200))
    residuals = rng.normal(size=200)
    xi, reason = solve(accumulate(jacobian, residuals))
    expected = np.linalg.lstsq(jacobian.T, -residuals, rcond=None)[0]
    assert reason == ""
    np.testing.assert_allclose(xi, expected, rtol=1e-9, atol=1e-12)


def test_a_single_plane_is_singular():
    # Points on the plane z = 2 with its normal: rotation about z and translation in x, y are
    # unconstrained, so the system has rank 3.
    u, v = np.meshgrid(np.linspace(-1, 1, 20), np.linspace(-1, 1, 20))
    world = np.stack([u.ravel(), v.ravel(), np.full(400, 2.0)])
    normals = np.tile([[0.0], [0.0], [-1.0]], (1, 400))
    jacobian, residuals = point_to_plane_rows(world, world + 0.01 * normals, normals)
    xi, reason = solve(accumulate(jacobian, residuals))
    assert xi is None and "singular" in reason


def test_too_few_correspondences_is_reported():
    xi, reason = solve(LinearSystem(np.eye(6), np.zeros(6), 3, 0.0), min_count=6)
    assert xi is None and "too few correspondences" in reason


def test_rejection_by_distance_and_normal_angle():
    camera = Intrinsics(10.0, 10.0, 1.5, 0.5, 4, 2)
    # Model: a wall 2 m ahead facing the camera, rendered from the identity pose.
    depth = np.full((2, 4), 2.0, dtype=np.float32)
    model_vertices = camera.backproject(depth)
    model_normals = np.zeros((2, 4, 3), dtype=np.float32)
    model_normals[..., 2] = -1.0
    # Current: the same pixels, pushed along the rays by 0.05 / 0.15 m, one normal tilted 25 deg.
    offsets = np.array([[0.05, 0.05, 0.15, 0.05], [0.05, 0.09, 0.11, 0.05]], dtype=np.float32)
    vertices = camera.backproject(depth + offsets)
    normals = model_normals.copy()
    tilt = np.radians(25.0)
    normals[1, 3] = [np.sin(tilt), 0.0, -np.cos(tilt)]
    normals[0, 3] = [np.sin(np.radians(15.0)), 0.0, -np.cos(np.radians(15.0))]
    model_x, model_n = (
        np.ascontiguousarray(model_vertices.reshape(-1, 3).T, dtype=np.float64),
        np.ascontiguousarray(model_normals.reshape(-1, 3).T, dtype=np.float64),
    )
    points, point_normals = valid_points(vertices, normals)
    world, matched, _ = associate(
        points, point_normals, np.eye(4), model_x, model_n, np.eye(4), camera, 0.10, 20.0
    )
    # Kept: 0.05 m offsets (incl. the 15 deg normal) and the 0.09 m one; rejected: 0.15 m and
    # 0.11 m (distance > 0.10 m; the rays are nearly along z so distance ~ offset) and the
    # 25 deg normal.
    distances = np.sort(np.linalg.norm(world - matched, axis=0))
    assert len(distances) == 5
    assert distances[-1] == pytest.approx(0.09, abs=2e-3)


def test_nan_model_pixels_are_never_matched(room_pair):
    previous, current, frame, model = room_pair
    holed = [(v.copy(), n.copy()) for v, n in model]
    for vertices, normals in holed:
        vertices[:, : vertices.shape[1] // 2] = np.nan
        normals[:, : normals.shape[1] // 2] = np.nan
    level = frame.levels[0]
    full, half = (
        icp_system(level.vertices, level.normals, current, *maps, previous, level.camera)
        for maps in (model[0], holed[0])
    )
    assert np.isfinite(half.A).all() and np.isfinite(half.b).all()
    # About half the image loses its model: between 30% and 70% of the pairs remain.
    assert 0.3 * full.count < half.count < 0.7 * full.count


def huber_loss(r: np.ndarray, k: float) -> np.ndarray:
    """Huber's rho: r^2 / 2 inside k, k |r| - k^2 / 2 beyond."""
    return np.where(np.abs(r) <= k, r * r / 2, k * np.abs(r) - k * k / 2)


def tukey_loss(r: np.ndarray, c: float) -> np.ndarray:
    """Tukey's biweight rho: c^2 / 6 (1 - (1 - (r / c)^2)^3) inside c, c^2 / 6 beyond."""
    inside = c * c / 6 * (1 - (1 - (r / c) ** 2) ** 3)
    return np.where(np.abs(r) < c, inside, c * c / 6)


@pytest.mark.parametrize(("kernel", "loss"), [("huber", huber_loss), ("tukey", tukey_loss)])
def test_robust_weights_are_the_losses_derivative_over_r(kernel, loss):
    # IRLS minimises sum rho(r) with weights w = rho'(r) / r: check against central differences
    # of the loss itself, on both sides of the threshold and on both signs.
    noise = 0.005
    threshold = robust_threshold(kernel, noise)
    r = np.array([-0.08, -0.03, -0.012, -0.004, 0.0007, 0.003, 0.009, 0.02, 0.05])
    h = 1e-8
    derivative = (loss(r + h, threshold) - loss(r - h, threshold)) / (2 * h)
    np.testing.assert_allclose(robust_weights(r, kernel, threshold), derivative / r, atol=1e-6)
    assert robust_weights(r, "none", threshold) is None  # least squares: every weight 1


def test_an_outlier_pair_gets_the_kernels_weight():
    # Residual spread 5 mm: Huber's k = 1.345 * 5 mm = 6.725 mm, Tukey's c = 23.425 mm.
    assert robust_threshold("huber", 0.005) == pytest.approx(0.006725)
    assert robust_threshold("tukey", 0.005) == pytest.approx(0.023425)
    r = np.array([0.002, 0.02, 0.03])
    # Inside k a pair keeps weight 1; at 2 cm Huber gives k / |r| = 0.33625 and Tukey
    # (1 - (20 / 23.425)^2)^2 = 0.0734653; at 3 cm, beyond c, Tukey drops the pair.
    np.testing.assert_allclose(robust_weights(r, "huber", 0.006725), [1.0, 0.33625, 0.22416667])
    np.testing.assert_allclose(
        robust_weights(r, "tukey", 0.023425), [0.98545, 0.0734653, 0.0], rtol=1e-4
    )
    # The weighted system is sum w J^T J: a Tukey-rejected pair adds nothing.
    world = np.array([[0.0, 0.1, 0.2], [0.0, 0.0, 0.1], [2.0, 2.0, 2.0]])
    normals = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 0.0], [-1.0, -1.0, -1.0]])
    model_vertices = world - normals * r  # (p - q) . n = r
    jacobian, residuals = point_to_plane_rows(world, model_vertices, normals)
    np.testing.assert_allclose(residuals, r, atol=1e-12)
    weighted = accumulate(jacobian, residuals, robust_weights(residuals, "tukey", 0.023425))
    first_two = accumulate(jacobian[:, :2], residuals[:2], robust_weights(r[:2], "tukey", 0.023425))
    np.testing.assert_allclose(weighted.A, first_two.A, atol=1e-15)


def test_depth_noise_weights_are_each_pairs_information():
    # sigma(z)^2 = axial(z)^2 + model^2, axial(z) = 1.2 mm + 1.9 mm (z - 0.4)^2 (Nguyen et al.):
    # 1.884 mm at 1 m, 14.044 mm at 3 m; a model noise of 3.4 mm (11.7 mm voxels / sqrt(12)).
    far_share = (0.001884**2 + 0.0034**2) / (0.014044**2 + 0.0034**2)  # 0.0724
    depths = np.array([1.0, 3.0])
    residuals = np.array([0.0, 0.006])
    # Least squares: each pair's weight is its information relative to a pair at 1 m.
    weights = pair_weights(residuals, depths, "none", 0.0, 0.0034)
    np.testing.assert_allclose(weights, [1.0, far_share], rtol=1e-4)
    assert pair_weights(residuals, depths, "none", 0.0) is None  # no noise model: every pair 1
    # Huber reads the far residual in units of the noise at 1 m: 6 mm * sqrt(0.0724) = 1.6 mm,
    # inside k = 6.7 mm, where without the noise model the pair lies in the linear tail.
    huber = pair_weights(residuals, depths, "huber", 0.006725, 0.0034)
    np.testing.assert_allclose(huber, [1.0, far_share], rtol=1e-4)
    # A far plane whose model lies 6 mm off and a true near plane, both frontal: the step along
    # the axis is the information-weighted mean of the residuals, 6 mm * w / (1 + w) = 0.405 mm
    # instead of least squares' 3 mm.
    world = np.array([[0.0, 0.0], [0.0, 0.0], depths])
    normals = np.array([[0.0, 0.0], [0.0, 0.0], [-1.0, -1.0]])
    jacobian, rows = point_to_plane_rows(world, world - normals * residuals, normals)
    for pair_weighting, expected in ((weights, 0.006 * far_share / (1 + far_share)), (None, 0.003)):
        system = accumulate(jacobian, rows, pair_weighting)
        step = -system.b[5] / system.A[5, 5]
        assert abs(step) == pytest.approx(expected, rel=1e-4)


def test_robust_kernels_ignore_a_foreground_object(room_pair):
    # A fifth of the current view (a block at the left) is moved 5 cm towards the camera, like an
    # object that the model does not hold: its pairs pass the 10 cm and 20 degree gates (normals
    # unchanged) and pull least squares off the true motion.
    previous, current, frame, model = room_pair

    def with_object(level):
        vertices = level.vertices.copy()
        height, width = vertices.shape[:2]
        block = (slice(height // 4, 3 * height // 4), slice(0, width // 5))
        lengths = np.linalg.norm(vertices[block], axis=-1, keepdims=True)
        vertices[block] *= 1 - 0.05 / lengths
        return dataclasses.replace(level, vertices=vertices)

    levels = [with_object(level) for level in frame.levels]
    errors = {}
    for kernel in ("none", "huber", "tukey"):
        problem = IcpProblem(levels, model, previous, robust_kernel=kernel)
        estimate, reason = refine(previous.copy(), problem.system, (10, 5, 4))
        assert reason == ""
        errors[kernel] = scene.pose_error(estimate, current)[0]
    # Least squares lands ~3 cm off; Huber bounds each outlier's pull (~8 mm); Tukey's c = 23 mm
    # gives the 5 cm pairs weight 0 at the truth, which is then an exact fixed point.
    assert errors["none"] > 20.0, errors
    assert errors["huber"] < errors["none"] / 3, errors
    assert errors["tukey"] < 0.01, errors
