"""RGB-D odometry (paper IV, Steinbruecker et al.) against independent truths: an analytic room
with known poses, finite differences of the photometric cost on images whose bilinear
interpolation is exact, brute-force interest points, closed-form weights."""

from __future__ import annotations

import numpy as np
import odometry_scene as scene
import pytest

from kintinuous_ref import se3
from kintinuous_ref.camera import Intrinsics
from kintinuous_ref.errors import ConfigError
from kintinuous_ref.odometry.rgbd import (
    RgbdProblem,
    correspond,
    interest_points,
    photometric_residuals,
    photometric_rows,
    prepare_level,
    robust_row_weights,
    sample_bilinear,
)
from kintinuous_ref.odometry.solve import refine


@pytest.fixture(scope="module")
def room_pair():
    previous, current = scene.room_poses()
    return previous, current, scene.frame(previous), scene.frame(current)


@pytest.mark.parametrize("gradient", ["current", "warped"])
def test_known_motion_is_recovered(room_pair, gradient):
    previous, current, previous_frame, current_frame = room_pair
    problem = RgbdProblem(previous_frame.levels, current_frame.levels, previous, gradient=gradient)
    estimate, reason = refine(previous.copy(), problem.system, (10, 7, 7, 7))
    assert reason == ""
    translation_mm, rotation_deg = scene.pose_error(estimate, current)
    # Noise-free: the brief's 1 mm / 0.1 degree (we observe ~0.05 mm / 0.001 degree; what is
    # left comes from the Sobel derivatives of the sampled texture).
    assert translation_mm < 1.0
    assert rotation_deg < 0.1
    assert problem.inlier_fraction(estimate) > 0.9


def test_interest_points_are_the_list_of_strong_gradients():
    rng = np.random.default_rng(4)
    dx = rng.normal(0, 8, (30, 40)).astype(np.float32)
    dy = rng.normal(0, 8, (30, 40)).astype(np.float32)
    indices = interest_points(dx, dy, 12.0)
    expected = [
        v * 40 + u for v in range(30) for u in range(40) if dx[v, u] ** 2 + dy[v, u] ** 2 >= 144
    ]
    assert indices.tolist() == expected  # a list of pixel indices in raster order, not a mask


def test_bilinear_sampling_of_a_plane_is_exact():
    v, u = np.mgrid[0:20, 0:30].astype(np.float64)
    image = 3.0 * u - 2.0 * v + 7.0
    su, sv = np.array([0.0, 12.25, 28.9, 29.0]), np.array([0.0, 3.5, 18.1, 19.0])
    np.testing.assert_allclose(sample_bilinear(image, su, sv), 3 * su - 2 * sv + 7, atol=1e-12)


def _ramp_scene():
    """A fronto-parallel wall at 2 m, intensity a linear ramp in the previous image.

    Bilinear interpolation of a linear image is exact and its gradient is the constant (a, b), so
    the analytic Jacobian must agree with finite differences to rounding error.
    """
    camera = Intrinsics(100.0, 100.0, 31.5, 23.5, 64, 48)
    v, u = np.mgrid[0:48, 0:64].astype(np.float64)
    depth = np.full((48, 64), 2.0, dtype=np.float32)
    previous_intensity = 0.8 * u - 0.5 * v + 60.0
    current_intensity = previous_intensity + np.random.default_rng(5).normal(0, 3, (48, 64))
    dx = np.full((48, 64), 0.8, dtype=np.float32)
    dy = np.full((48, 64), -0.5, dtype=np.float32)
    points = prepare_level(depth, current_intensity, dx, dy, camera, 0.5, 6.0)
    return camera, depth, previous_intensity, dx, dy, points


def test_jacobian_matches_finite_differences():
    camera, depth, previous_intensity, dx, dy, points = _ramp_scene()
    previous_pose = se3.exp(np.array([0.02, -0.01, 0.03, 0.1, 0.2, -0.1]))
    pose = previous_pose @ se3.exp(np.array([0.01, 0.005, -0.01, 0.02, -0.01, 0.03]))
    pairs = correspond(points, pose, previous_pose, depth, previous_intensity, camera, 0.07, dx, dy)
    assert len(pairs.kept) > 1000
    jacobian, residuals = photometric_rows(pairs, previous_pose, camera)
    args = (points, pairs.kept, pose, previous_pose, previous_intensity, camera)
    np.testing.assert_allclose(residuals, photometric_residuals(np.zeros(6), *args), atol=1e-9)
    step = 1e-6
    for k in range(6):
        xi = np.zeros(6)
        xi[k] = step
        numeric = (photometric_residuals(xi, *args) - photometric_residuals(-xi, *args)) / (
            2 * step
        )
        # Exact bilinear interpolation of a plane: only rounding (~1e-7 relative) remains.
        np.testing.assert_allclose(jacobian[k], numeric, rtol=1e-5, atol=1e-4)


def test_current_gradient_jacobian_agrees_at_alignment():
    # The paper's default uses the current image's gradient at p; when the frames are aligned and
    # the images identical it coincides with the exact derivative.
    camera, depth, previous_intensity, dx, dy, _ = _ramp_scene()
    points = prepare_level(depth, previous_intensity, dx, dy, camera, 0.5, 6.0)
    pose = se3.exp(np.array([0.02, -0.01, 0.03, 0.1, 0.2, -0.1]))
    exact = correspond(points, pose, pose, depth, previous_intensity, camera, 0.07, dx, dy)
    paper = correspond(points, pose, pose, depth, previous_intensity, camera, 0.07)
    np.testing.assert_allclose(
        photometric_rows(exact, pose, camera)[0], photometric_rows(paper, pose, camera)[0]
    )


def test_robust_weights_follow_the_normalised_difference():
    residuals = np.array([3.0, -4.0, 0.0, 12.0])
    sigma = np.sqrt(np.mean(residuals**2))  # sigma' = sqrt(sum r^2 / k_c) = sqrt(169 / 4) = 6.5
    assert sigma == pytest.approx(6.5)
    np.testing.assert_allclose(
        robust_row_weights(residuals), [1 / 9.5, 1 / 10.5, 1 / 6.5, 1 / 18.5]
    )


def test_depth_change_rejects_occlusions():
    camera, depth, previous_intensity, dx, dy, points = _ramp_scene()
    occluded = depth.copy()
    occluded[:, :32] = 1.9  # 0.10 m in front of the wall in the left half: fails d_s = 0.07 m
    pairs = correspond(points, np.eye(4), np.eye(4), occluded, previous_intensity, camera, 0.07)
    u = points.indices[pairs.kept] % 64
    assert len(pairs.kept) > 0
    # Warping with the identity keeps pixels in place (rounding picks the pixel itself).
    assert u.min() >= 32
    slight = depth.copy()
    slight[:, :32] = 1.95  # 0.05 m: passes
    pairs = correspond(points, np.eye(4), np.eye(4), slight, previous_intensity, camera, 0.07)
    assert len(pairs.kept) == len(points.indices)


def test_unknown_gradient_mode_is_a_config_error(room_pair):
    _, _, previous_frame, current_frame = room_pair
    with pytest.raises(ConfigError, match="rgbd.gradient"):
        RgbdProblem(previous_frame.levels, current_frame.levels, np.eye(4), gradient="sobel")
