"""Properties of the SE(3) maps on random poses: round trips, inverses, small-angle limits."""

import numpy as np
import pytest

from kintinuous_ref import se3


def random_twist(rng, angle_scale=1.0, translation_scale=1.0):
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    angle = rng.uniform(0.0, np.pi * 0.999) * angle_scale
    return np.concatenate([axis * angle, rng.normal(size=3) * translation_scale])


@pytest.fixture
def rng():
    return np.random.default_rng(7)


def test_exp_of_pure_translation_is_translation():
    pose = se3.exp(np.array([0, 0, 0, 0.1, -0.2, 0.3]))
    expected = np.eye(4)
    expected[:3, 3] = [0.1, -0.2, 0.3]
    np.testing.assert_allclose(pose, expected)


def test_exp_rotation_about_z_matches_closed_form():
    angle = 0.7
    pose = se3.exp(np.array([0, 0, angle, 0, 0, 0]))
    c, s = np.cos(angle), np.sin(angle)
    np.testing.assert_allclose(pose[:3, :3], [[c, -s, 0], [s, c, 0], [0, 0, 1]], atol=1e-15)


def test_exp_matches_scipy_matrix_exponential(rng):
    from scipy.linalg import expm

    for _ in range(50):
        xi = random_twist(rng)
        xi_hat = np.zeros((4, 4))
        xi_hat[:3, :3] = se3.skew(xi[:3])
        xi_hat[:3, 3] = xi[3:]
        np.testing.assert_allclose(se3.exp(xi), expm(xi_hat), atol=1e-12)


@pytest.mark.parametrize("angle_scale", [1.0, 1e-2, 1e-3, 1e-5, 1e-7, 0.0])
def test_log_inverts_exp(rng, angle_scale):
    for _ in range(100):
        xi = random_twist(rng, angle_scale)
        np.testing.assert_allclose(se3.log(se3.exp(xi)), xi, atol=1e-12)


def test_log_near_pi_recovers_axis(rng):
    for _ in range(20):
        axis = rng.normal(size=3)
        axis /= np.linalg.norm(axis)
        xi = np.concatenate([axis * (np.pi - 1e-9), [0.1, 0.2, 0.3]])
        pose = se3.exp(xi)
        np.testing.assert_allclose(se3.exp(se3.log(pose)), pose, atol=1e-7)


def test_small_angle_limit_is_first_order(rng):
    xi = random_twist(rng, angle_scale=1e-8, translation_scale=1e-8)
    xi_hat = np.zeros((4, 4))
    xi_hat[:3, :3] = se3.skew(xi[:3])
    xi_hat[:3, 3] = xi[3:]
    np.testing.assert_allclose(se3.exp(xi), np.eye(4) + xi_hat, atol=1e-15)


def test_inverse_and_compose(rng):
    for _ in range(50):
        a, b = se3.exp(random_twist(rng)), se3.exp(random_twist(rng))
        np.testing.assert_allclose(se3.compose(a, se3.inverse(a)), np.eye(4), atol=1e-12)
        np.testing.assert_allclose(
            se3.inverse(se3.compose(a, b)), se3.compose(se3.inverse(b), se3.inverse(a)), atol=1e-12
        )


def test_tum_round_trip(rng):
    for _ in range(100):
        pose = se3.exp(random_twist(rng))
        np.testing.assert_allclose(se3.from_tum(se3.to_tum(pose)), pose, atol=1e-12)


def test_tum_quaternion_convention():
    # 90 degrees about z: q = (0, 0, sin 45, cos 45), TUM order qx qy qz qw.
    pose = se3.from_tum(np.array([1, 2, 3, 0, 0, np.sqrt(0.5), np.sqrt(0.5)]))
    np.testing.assert_allclose(pose[:3, :3] @ [1, 0, 0], [0, 1, 0], atol=1e-15)
    np.testing.assert_allclose(pose[:3, 3], [1, 2, 3])


def test_invalid_inputs_raise_pose_error():
    with pytest.raises(se3.PoseError, match="6 entries"):
        se3.exp(np.zeros(5))
    with pytest.raises(se3.PoseError, match="not a rigid motion"):
        se3.inverse(np.diag([1.0, 2.0, 1.0, 1.0]))
    with pytest.raises(se3.PoseError, match="no direction"):
        se3.from_tum(np.zeros(7))
