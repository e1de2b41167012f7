"""ICP + RGB-D (paper eq. 11-13): the joint system is the weighted sum of its parts, equals the
stacked least-squares problem built independently, and recovers motion where ICP alone cannot."""

from __future__ import annotations

import numpy as np
import odometry_scene as scene
import pytest

from kintinuous_ref import se3
from kintinuous_ref.errors import ConfigError
from kintinuous_ref.odometry.combined import CombinedProblem, joint_system
from kintinuous_ref.odometry.icp import IcpProblem, associate, point_to_plane_rows
from kintinuous_ref.odometry.rgbd import RgbdProblem, correspond, photometric_rows
from kintinuous_ref.odometry.solve import refine


def pose_error(estimate: np.ndarray, truth: np.ndarray) -> tuple[float, float]:
    difference = se3.inverse(truth) @ estimate
    return 1000 * float(np.linalg.norm(difference[:3, 3])), float(
        np.degrees(se3.rotation_angle(difference[:3, :3]))
    )


@pytest.fixture(scope="module")
def room():
    previous = scene.look_pose([0.1, -0.1, 0.2], 5, -10)
    current = previous @ se3.exp(np.array([0.01, -0.02, 0.015, 0.02, -0.01, 0.03]))
    previous_frame, current_frame = scene.frame(previous, levels=3), scene.frame(current, levels=3)
    icp = IcpProblem(current_frame.levels, scene.model(previous), previous)
    rgbd = RgbdProblem(previous_frame.levels, current_frame.levels, previous)
    return previous, current, icp, rgbd


def test_joint_system_is_the_weighted_sum(room):
    previous, current, icp, rgbd = room
    # A pose between the two frames, so that both residuals are non-zero.
    pose = previous @ se3.exp(0.5 * se3.log(se3.inverse(previous) @ current))
    a, b = icp.system(1, pose), rgbd.system(1, pose)
    # Default: E_icp / sigma_icp^2 + w E_rgbd, sigma_icp^2 the mean squared ICP residual.
    sigma2 = a.cost / a.count
    joint = CombinedProblem(icp, rgbd, rgbd_weight=0.1).system(1, pose)
    np.testing.assert_allclose(joint.A, a.A / sigma2 + 0.1 * b.A, rtol=1e-12)
    np.testing.assert_allclose(joint.b, a.b / sigma2 + 0.1 * b.b, rtol=1e-12)
    assert joint.count == a.count + b.count
    # "paper-metres": the literal sum with E_icp in square metres.
    metres = CombinedProblem(icp, rgbd, 0.1, weighting="paper-metres").system(1, pose)
    np.testing.assert_allclose(metres.A, a.A + 0.1 * b.A, rtol=1e-12)
    np.testing.assert_allclose(metres.b, a.b + 0.1 * b.b, rtol=1e-12)


def test_joint_system_equals_the_stacked_least_squares(room):
    # Eq. 12: [J_icp / s; v J_rgbd] xi = -[r_icp / s; v r_rgbd] with v = sqrt(w) and s the RMS ICP
    # residual, built here from the rows directly (the RGB-D rows carrying their robust weights
    # 1 / (sigma' + |r|)).
    previous, current, icp, rgbd = room
    pose = previous @ se3.exp(0.5 * se3.log(se3.inverse(previous) @ current))
    level = icp.current_levels[1]
    world, matched, normals = associate(
        *icp.points(1), pose, *icp.model(1), previous, level.camera, 0.10, 20.0
    )
    j_icp, r_icp = point_to_plane_rows(world, matched, normals)
    prev_level = rgbd.previous_levels[1]
    pairs = correspond(
        rgbd.points(1), pose, previous, prev_level.depth, prev_level.intensity, level.camera, 0.07
    )
    j_rgbd, r_rgbd = photometric_rows(pairs, previous, level.camera)
    sigma = np.sqrt(np.mean(r_rgbd**2))
    row_weight = 1.0 / (sigma + np.abs(r_rgbd))
    v = np.sqrt(0.1)
    icp_rms = np.sqrt(np.mean(r_icp**2))
    stacked_j = np.concatenate([j_icp.T / icp_rms, v * row_weight[:, None] * j_rgbd.T])
    stacked_r = np.concatenate([r_icp / icp_rms, v * row_weight * r_rgbd])
    expected_step = np.linalg.lstsq(stacked_j, -stacked_r, rcond=None)[0]
    joint = CombinedProblem(icp, rgbd, 0.1).system(1, pose)
    np.testing.assert_allclose(joint.A, stacked_j.T @ stacked_j, rtol=1e-9)
    np.testing.assert_allclose(np.linalg.solve(joint.A, -joint.b), expected_step, rtol=1e-6)


def test_original_code_weighting(room):
    previous, _, icp, rgbd = room
    a, b = icp.system(2, previous), rgbd.system(2, previous)
    joint = joint_system(a, b, weighting="original-code", original_code_icp_scale=10.0)
    np.testing.assert_allclose(joint.A, b.A + 100.0 * a.A, rtol=1e-12)
    np.testing.assert_allclose(joint.b, b.b + 10.0 * a.b, rtol=1e-12)
    with pytest.raises(ConfigError, match="weighting"):
        joint_system(a, b, weighting="average")


def test_known_motion_is_recovered(room):
    previous, current, icp, rgbd = room
    estimate, reason = refine(previous.copy(), CombinedProblem(icp, rgbd).system, (10, 5, 4))
    assert reason == ""
    translation_mm, rotation_deg = pose_error(estimate, current)
    assert translation_mm < 1.0 and rotation_deg < 0.1  # noise-free: 1 mm / 0.1 degree


def test_corridor_icp_is_singular_and_joint_holds():
    # Along a corridor every normal is perpendicular to the walking direction: ICP's system loses
    # that degree of freedom (the paper's "slipping"), the texture keeps it.
    previous = scene.look_pose([0.1, -0.1, -0.5], 3, -4)
    current = previous @ se3.exp(np.array([0.005, -0.01, 0.005, 0.005, -0.005, 0.04]))
    walls = scene.CORRIDOR
    previous_frame = scene.frame(previous, levels=3, walls=walls)
    current_frame = scene.frame(current, levels=3, walls=walls)
    icp = IcpProblem(current_frame.levels, scene.model(previous, walls=walls), previous)
    _, reason = refine(previous.copy(), icp.system, (10, 5, 4))
    assert "singular" in reason
    rgbd = RgbdProblem(previous_frame.levels, current_frame.levels, previous)
    estimate, reason = refine(previous.copy(), CombinedProblem(icp, rgbd).system, (10, 5, 4))
    assert reason == ""
    translation_mm, rotation_deg = pose_error(estimate, current)
    assert translation_mm < 1.0 and rotation_deg < 0.1
