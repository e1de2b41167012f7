"""A loop's covariance from its own alignment: the change of frame from the alignment's
increment to the pose graph's residual against closed forms, and the bounds on the covariance."""

from __future__ import annotations

import numpy as np
import pytest

from kintinuous_ref import se3
from kintinuous_ref.config import LoopClosureConfig
from kintinuous_ref.loop_closure import calibration, place_recognition

SETTINGS = LoopClosureConfig()
# a loop's relative pose: 24 cm and about 11 degrees, like redkitchen's offset return
LOOP = se3.exp(np.array([0.05, -0.18, 0.04, 0.21, -0.05, 0.1]))


def test_the_adjoint_moves_a_twist_through_a_pose():
    xi = np.array([0.02, -0.01, 0.03, 0.05, 0.01, -0.02])
    moved = LOOP @ se3.exp(xi) @ se3.inverse(LOOP)
    np.testing.assert_allclose(moved, se3.exp(place_recognition.adjoint(LOOP) @ xi), atol=1e-12)


def test_an_increment_of_the_alignment_is_the_residual_the_pose_graph_sees():
    # Z = exp(xi) Z_graph: the graph's residual log(Z^-1 Z_graph) is -Ad(Z^-1) xi to first order
    xi = 1e-6 * np.array([3.0, -1.0, 2.0, 5.0, 1.0, -4.0])
    measured = se3.exp(xi) @ LOOP
    residual = calibration.pose_residual(measured, LOOP)
    expected = -place_recognition.adjoint(se3.inverse(measured)) @ xi
    np.testing.assert_allclose(residual, expected, atol=1e-10)  # second order: 1e-11
    # and an information of xi, moved to the residual, gives the same chi^2
    rng = np.random.default_rng(0)
    root = rng.normal(size=(6, 6))
    information = root @ root.T + np.eye(6)
    moved = place_recognition.residual_information(information, measured)
    assert residual @ moved @ residual == pytest.approx(xi @ information @ xi, rel=1e-4)


def test_a_loop_covariance_is_its_information_inverted_within_the_bounds():
    sigmas = np.array([np.radians(0.3)] * 3 + [0.02] * 3)  # within the floor and the ceiling
    per_pair = np.diag(1 / sigmas**2) / SETTINGS.loop_effective_pairs
    covariance = place_recognition.loop_covariance(per_pair, SETTINGS)
    np.testing.assert_allclose(np.sqrt(np.diag(covariance)), sigmas, rtol=1e-9)
    # a perfect alignment is held to the floor, an unconstrained direction to the ceiling
    certain = place_recognition.loop_covariance(np.eye(6) * 1e12, SETTINGS)
    floor = [np.radians(SETTINGS.loop_sigma_floor_rotation_deg)] * 3
    floor += [SETTINGS.loop_sigma_floor_translation] * 3
    np.testing.assert_allclose(np.sqrt(np.diag(certain)), floor, rtol=1e-9)
    blind = np.diag(1 / sigmas**2) / SETTINGS.loop_effective_pairs
    blind[3, 3] = 0.0  # nothing along x
    loose = place_recognition.loop_covariance(blind, SETTINGS)
    assert np.sqrt(loose[3, 3]) == pytest.approx(
        SETTINGS.loop_sigma_ceiling * SETTINGS.loop_sigma_floor_translation
    )
    assert np.all(np.linalg.eigvalsh(loose) > 0)
