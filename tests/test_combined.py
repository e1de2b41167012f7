"""ICP + RGB-D (paper eq. 11-13): the joint system is the weighted sum of its parts, equals the
stacked least-squares problem built independently, and recovers motion where ICP alone cannot."""

from __future__ import annotations

import numpy as np
import odometry_scene as scene
import pytest

from kintinuous_ref import se3
from kintinuous_ref.config import Config, VolumeConfig, with_overrides
from kintinuous_ref.errors import ConfigError
from kintinuous_ref.odometry.combined import (
    CombinedProblem,
    discount_weak_directions,
    icp_model_noise,
    icp_scale,
    information_spectrum,
    joint_system,
)
from kintinuous_ref.odometry.icp import IcpProblem, associate, point_to_plane_rows
from kintinuous_ref.odometry.rgbd import RgbdProblem, correspond, photometric_rows
from kintinuous_ref.odometry.solve import accumulate, refine, solve


@pytest.fixture(scope="module")
def room():
    previous, current = scene.room_poses()
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
    translation_mm, rotation_deg = scene.pose_error(estimate, current)
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
    translation_mm, rotation_deg = scene.pose_error(estimate, current)
    assert translation_mm < 1.0 and rotation_deg < 0.1


def corridor_systems(camera: np.ndarray, truth: np.ndarray):
    """ICP rows of a corridor along world z (walls x = +-1, floor and ceiling y = +-1 around the
    camera) with 2 % stray normals that pull 20 mm along z, and exact-but-noisy RGB-D rows that
    see every direction: the case the degeneracy-aware weighting is for."""
    rng = np.random.default_rng(0)
    count = 4000
    side, across = rng.integers(0, 4, count), rng.uniform(-1, 1, count)
    points, normals = np.zeros((3, count)), np.zeros((3, count))
    for k, (axis, sign) in enumerate(((0, 1), (0, -1), (1, 1), (1, -1))):
        wall = side == k
        normals[axis, wall] = -sign
        points[axis, wall] = camera[axis] + sign
        points[1 - axis, wall] = camera[1 - axis] + across[wall]
    points[2] = camera[2] + rng.uniform(0.5, 6, count)
    stray = rng.choice(count, count // 50, replace=False)
    normals[:, stray] += rng.normal(0, 0.3, (3, stray.size)) + np.array([[0], [0], [0.5]])
    normals /= np.linalg.norm(normals, axis=0)
    jacobian = np.concatenate([np.cross(points, normals, axis=0), normals])
    residuals = -(jacobian.T @ truth) + rng.normal(0, 0.002, count)
    residuals[stray] += 0.02
    # photometric rows carry ~2e3 per pair here (real frames: 1e4-1e5 in the scaled coordinates)
    photometric = rng.normal(0, 40, (6, 3000)) * np.array([[3, 3, 3, 1, 1, 1]]).T
    rgbd = accumulate(photometric, -(photometric.T @ truth) + rng.normal(0, 0.4, 3000))
    return accumulate(jacobian, residuals), rgbd, points, normals, residuals


def test_degeneracy_aware_leaves_the_corridor_direction_to_rgbd():
    camera = np.array([5.0, -3.0, 10.0])
    truth = np.array([0.002, -0.001, 0.003, 0.01, -0.02, 0.015])
    icp, rgbd, *_ = corridor_systems(camera, truth)
    eigenvalues, eigenvectors, _ = information_spectrum(icp, camera)
    # one direction observed by ~0.4 % of the pairs: the translation along the corridor (the
    # rotations, observed by 2-5 %, stay with ICP under this threshold)
    threshold = 0.02
    assert eigenvalues[0] < threshold < eigenvalues[1]
    assert abs(eigenvectors[5, 0]) > 0.99
    along = {}
    for weighting in ("paper", "degeneracy-aware"):
        xi, reason = solve(
            joint_system(
                icp, rgbd, 1.0, weighting, camera_position=camera, degeneracy_threshold=threshold
            )
        )
        assert reason == ""
        along[weighting] = abs(xi[5] - truth[5])
    rgbd_alone, _ = solve(rgbd)
    icp_alone, _ = solve(icp)
    assert abs(icp_alone[5] - truth[5]) > 0.03  # ICP alone slides with its stray normals
    # the sum is still pulled by them; with ICP's say along the corridor cut to a fifth (its
    # share, 0.4 %, over the threshold) the estimate there is nearly RGB-D's
    assert along["paper"] > 1.5 * along["degeneracy-aware"]
    assert along["degeneracy-aware"] < 1.2 * abs(rgbd_alone[5] - truth[5])
    # a threshold of 0 leaves the system as it is; otherwise ICP alone keeps its minimiser (in
    # the dark, with no partner, ICP still decides every direction as before)
    assert discount_weak_directions(icp, camera, 0.0) is icp
    discounted = discount_weak_directions(icp, camera, threshold)
    assert not np.allclose(discounted.A, icp.A)
    np.testing.assert_allclose(solve(discounted)[0], icp_alone, rtol=1e-6, atol=1e-9)


def test_a_weaker_partner_still_decides_the_unobserved_direction():
    # RGB-D's robust weights follow its RMS residual, so its information can drop tenfold for a
    # few frames. A gate that compares the two terms 1:1 would then hand the corridor back to
    # ICP whole; discounted by its share (0.4 % against 2 %), ICP's biased sliver counts for a
    # fifth, less than a partner holding half of its undiscounted information there.
    camera = np.array([5.0, -3.0, 10.0])
    truth = np.array([0.002, -0.001, 0.003, 0.01, -0.02, 0.015])
    icp, rgbd, *_ = corridor_systems(camera, truth)
    eigenvalues, eigenvectors, to_scaled = information_spectrum(icp, camera)
    icp_along = eigenvalues[0] * icp.count / icp_scale(icp) ** 2
    direction = to_scaled @ eigenvectors[:, 0]
    weaker = rgbd.scaled(0.5 * icp_along / float(direction @ rgbd.A @ direction))
    errors = {}
    for weighting in ("paper", "degeneracy-aware"):
        system = joint_system(
            icp, weaker, weighting=weighting, camera_position=camera, degeneracy_threshold=0.02
        )
        errors[weighting] = abs(solve(system)[0][5] - truth[5])
    icp_alone, _ = solve(icp)
    # ICP's pull is its weight's share of its own error: 2/3 of it undiscounted, 2/7 discounted
    assert errors["paper"] > 0.6 * abs(icp_alone[5] - truth[5])
    assert errors["degeneracy-aware"] < 0.35 * abs(icp_alone[5] - truth[5])


def test_information_spectrum_does_not_depend_on_the_world_origin():
    camera, truth = np.array([5.0, -3.0, 10.0]), np.zeros(6)
    icp, _, points, normals, residuals = corridor_systems(camera, truth)
    offset = np.array([[-40.0], [12.0], [7.0]])
    moved = accumulate(
        np.concatenate([np.cross(points + offset, normals, axis=0), normals]), residuals
    )
    np.testing.assert_allclose(
        information_spectrum(moved, camera + offset[:, 0])[0],
        information_spectrum(icp, camera)[0],
        rtol=1e-8,
        atol=1e-12,
    )


def test_information_and_elasticfusion_weightings(room):
    previous, current, icp, rgbd = room
    pose = previous @ se3.exp(0.5 * se3.log(se3.inverse(previous) @ current))
    a, b = icp.system(1, pose), rgbd.system(1, pose)
    joint = joint_system(a, b, 0.5, "information")
    expected = a.A / (a.cost / a.count) + 0.5 * b.A / (b.cost / b.count)
    np.testing.assert_allclose(joint.A, expected, rtol=1e-12)
    # ElasticFusion combines A_rgbd + w^2 A_icp, b_rgbd + w b_icp: the authors' Kintinuous code
    ef = joint_system(a, b, weighting="elasticfusion", original_code_icp_scale=10.0)
    np.testing.assert_allclose(ef.A, b.A + 100 * a.A, rtol=1e-12)
    np.testing.assert_allclose(ef.b, b.b + 10 * a.b, rtol=1e-12)


def test_the_combined_inlier_check_stands_on_either_term(room):
    # A model that covers only a strip of the view (the rest beyond the volume): ICP matches
    # under 10 % of its vertices, RGB-D most of its interest points; the joint estimate stands.
    previous, current, icp, rgbd = room
    strip = []
    for vertices, normals in scene.model(previous):
        vertices, normals = vertices.copy(), normals.copy()
        vertices[:, vertices.shape[1] // 16 :] = np.nan
        normals[:, normals.shape[1] // 16 :] = np.nan
        strip.append((vertices, normals))
    narrow = IcpProblem(icp.current_levels, strip, previous)
    icp_fraction = narrow.inlier_fraction(current)
    rgbd_fraction = rgbd.inlier_fraction(current)
    assert icp_fraction < 0.1 < rgbd_fraction
    combined = CombinedProblem(narrow, rgbd)
    assert combined.inlier_fraction(current) == rgbd_fraction


def test_the_combined_inlier_check_counts_icp_only_where_rgbd_falls_short(room, monkeypatch):
    # The check asks whether either term reaches the least fraction: where RGB-D's does, ICP's
    # pairs (a pass over every valid point) are not counted; below it, the larger of the two.
    previous, current, icp, rgbd = room
    icp_fraction, rgbd_fraction = icp.inlier_fraction(current), rgbd.inlier_fraction(current)
    assert 0.9 < icp_fraction < rgbd_fraction < 0.99
    counted = []
    count_icp = icp.inlier_fraction
    monkeypatch.setattr(icp, "inlier_fraction", lambda *a: counted.append(a) or count_icp(*a))
    combined = CombinedProblem(icp, rgbd)
    assert combined.inlier_fraction(current, enough=0.1) == rgbd_fraction
    assert combined.inlier_fraction(current, enough=rgbd_fraction) == rgbd_fraction
    assert counted == []
    for enough in (0.99, None):  # RGB-D's short of it, or no bound: both counted
        assert combined.inlier_fraction(current, enough=enough) == rgbd_fraction
    assert counted == [(current, 0), (current, 0)]


@pytest.mark.parametrize("kernel", ["huber", "tukey"])
def test_robust_weightings_are_degeneracy_aware_on_robust_icp_rows(room, kernel):
    # combined.weighting "huber" / "tukey": the default combination of the robustly weighted ICP
    # system; the tracker gives the ICP problem that kernel whatever icp.robust_kernel says.
    from kintinuous_ref.config import Config, with_overrides
    from kintinuous_ref.odometry.combined import icp_robust_kernel

    previous, current, icp, rgbd = room
    pose = previous @ se3.exp(0.5 * se3.log(se3.inverse(previous) @ current))
    robust = IcpProblem(icp.current_levels, icp.model_levels, previous, robust_kernel=kernel)
    a, b = robust.system(1, pose), rgbd.system(1, pose)
    assert not np.allclose(a.A, icp.system(1, pose).A, rtol=1e-3)  # the kernel acts here
    joint = CombinedProblem(robust, rgbd, weighting=kernel).system(1, pose)
    expected = joint_system(a, b, weighting="degeneracy-aware", camera_position=pose[:3, 3])
    np.testing.assert_allclose(joint.A, expected.A, rtol=1e-12)
    np.testing.assert_allclose(joint.b, expected.b, rtol=1e-12)
    config = with_overrides(Config(), {"combined.weighting": kernel, "icp.robust_kernel": "none"})
    assert icp_robust_kernel("icp+rgbd", config) == kernel
    assert icp_robust_kernel("icp", config) == "none"  # icp alone reads icp.robust_kernel
    alone = with_overrides(
        Config(), {"icp.robust_kernel": kernel, "combined.weighting": "degeneracy-aware"}
    )
    assert icp_robust_kernel("icp", alone) == kernel
    assert icp_robust_kernel("icp+rgbd", alone) == "none"  # a named weighting is one system
    with pytest.raises(ConfigError, match="icp.robust_kernel"):
        with_overrides(Config(), {"icp.robust_kernel": "cauchy"})
    with pytest.raises(ConfigError, match="robust_noise"):
        IcpProblem(
            icp.current_levels, icp.model_levels, previous, robust_kernel="tukey", robust_noise=0
        )


def test_the_depth_noise_model_follows_the_voxels_and_the_weighting():
    # icp alone and the robust weightings of icp+rgbd weigh pairs by the noise at their depth,
    # the model's part a uniform error over one voxel (voxel / sqrt(12)); the least-squares
    # weightings keep the system their name fixes; icp.depth_noise = False turns it off.
    config = Config(volume=VolumeConfig(resolution=256, size=3.0))
    voxel_noise = 3.0 / 256 / np.sqrt(12.0)
    assert icp_model_noise("icp", config) == pytest.approx(voxel_noise)
    assert icp_model_noise("icp+rgbd", config) == pytest.approx(voxel_noise)  # "huber"
    paper = with_overrides(config, {"combined.weighting": "paper"})
    assert icp_model_noise("icp+rgbd", paper) is None
    assert icp_model_noise("icp", with_overrides(config, {"icp.depth_noise": False})) is None
