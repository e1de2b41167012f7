"""Trajectory metrics against evo (the community's ATE/RPE implementation), closed forms and a
hand-computed ranking score; the `kintinuous evaluate` command against evo reading the same files.

Tolerance against evo: 1e-6 (metres, degrees, m/s). Both sides compute in float64 from the same
poses; what differs is the order of operations (SVD, products), worth ~1e-12.

evo 1.38 has no time-based RPE delta (Unit.seconds raises FilterException "unsupported delta
unit"). Our drift pairs j with the pose closest to t_i + 1 s, for every i with t_i + 1 s inside the
trajectory; on a uniformly sampled 30 Hz trajectory that is exactly evo's all-pairs index delta of
30 frames (i, i + 30 for i + 30 < n), which is what the drift tests compare against. If a future
evo accepts Unit.seconds, the tests compare against that as well.
"""

import json

import numpy as np
import pytest
from evo.core import filters, sync
from evo.core import metrics as evo_metrics
from evo.core.trajectory import PoseTrajectory3D
from evo.core.units import Unit
from evo.tools import file_interface

from kintinuous_ref import metrics, se3
from kintinuous_ref.datasets.tum import Trajectory, write_trajectory
from kintinuous_ref.program.cli import main

KEYS = {
    "ate_rmse",
    "ate_median",
    "ate_max",
    "rpe_trans_median",
    "rpe_trans_max",
    "rpe_rot_median_deg",
    "rpe_rot_max_deg",
    "drift_rmse_m_per_s",
    "pairs",
}
EVO_TOLERANCE = 1e-6


def smooth_pose(t: np.ndarray, seed: int = 0) -> np.ndarray:
    """A smooth camera path: sums of sinusoids in position (metres) and rotation vector (rad)."""
    rng = np.random.default_rng(seed)
    amplitude = rng.uniform(0.2, 1.0, (2, 3))
    frequency = rng.uniform(0.1, 0.6, (2, 3))
    phase = rng.uniform(0, 2 * np.pi, (2, 3))
    waves = amplitude * np.sin(frequency * t[:, None, None] + phase)  # (N, 2, 3)
    poses = np.array([se3.exp(np.concatenate([0.6 * w[0], w[1]])) for w in waves])
    return poses


def make_pair(drop: bool, seed: int = 0) -> tuple[Trajectory, Trajectory]:
    """Ground truth at 30 Hz over 8 s; an estimate with drift, noise, an arbitrary world frame,
    timestamps offset by 6 ms, poses before and after the ground truth (unmatched) and, with
    `drop`, missing frames, so that association decides which poses are compared."""
    rng = np.random.default_rng(seed + 100)
    gt_times = 1.0 + np.arange(241) / 30.0
    est_times = 1.006 + np.arange(-15, 256) / 30.0
    if drop:
        est_times = np.delete(est_times, rng.choice(len(est_times), 40, replace=False))
    world = se3.exp(np.array([0.3, -1.0, 0.5, 2.0, 1.0, -0.5]))  # estimate's own world frame
    drift = np.array([0.01, -0.02, 0.015, 0.03, 0.01, -0.02])  # per second
    estimate = []
    for t, pose in zip(est_times, smooth_pose(est_times - 1.0, seed), strict=True):
        noise = se3.exp(np.concatenate([rng.normal(0, 0.003, 3), rng.normal(0, 0.008, 3)]))
        estimate.append(world @ se3.exp(drift * (t - 1.0)) @ pose @ noise)
    return (
        Trajectory(est_times, np.array(estimate)),
        Trajectory(gt_times, smooth_pose(gt_times - 1.0, seed)),
    )


def evo_trajectory(trajectory: Trajectory) -> PoseTrajectory3D:
    return PoseTrajectory3D(timestamps=trajectory.timestamps, poses_se3=list(trajectory.poses))


def evo_drift_rmse(ref: PoseTrajectory3D, est: PoseTrajectory3D) -> float:
    """RPE translation RMSE over 1 s: evo's time delta if it has one, else 30 frames (see top)."""
    try:
        rpe = evo_metrics.RPE(
            evo_metrics.PoseRelation.translation_part, 1.0, Unit.seconds, all_pairs=True
        )
        rpe.process_data((ref, est))
    except (filters.FilterException, evo_metrics.MetricsException):
        rpe = evo_metrics.RPE(
            evo_metrics.PoseRelation.translation_part, 30, Unit.frames, all_pairs=True
        )
        rpe.process_data((ref, est))
    return rpe.get_statistic(evo_metrics.StatisticsType.rmse)


def evo_errors(ref: PoseTrajectory3D, est: PoseTrajectory3D, drift: bool) -> dict[str, float]:
    """Our keys computed by evo: associate (0.02 s), align without scale, APE, RPE 1 frame."""
    ref, est = sync.associate_trajectories(ref, est, max_diff=0.02)
    result = {"pairs": ref.num_poses}
    frame_translation = evo_metrics.RPE(evo_metrics.PoseRelation.translation_part, 1, Unit.frames)
    frame_translation.process_data((ref, est))
    frame_rotation = evo_metrics.RPE(evo_metrics.PoseRelation.rotation_angle_deg, 1, Unit.frames)
    frame_rotation.process_data((ref, est))
    if drift:
        result["drift_rmse_m_per_s"] = evo_drift_rmse(ref, est)
    est.align(ref, correct_scale=False)
    ape = evo_metrics.APE(evo_metrics.PoseRelation.translation_part)
    ape.process_data((ref, est))
    stats = evo_metrics.StatisticsType
    result |= {
        "ate_rmse": ape.get_statistic(stats.rmse),
        "ate_median": ape.get_statistic(stats.median),
        "ate_max": ape.get_statistic(stats.max),
        "rpe_trans_median": frame_translation.get_statistic(stats.median),
        "rpe_trans_max": frame_translation.get_statistic(stats.max),
        "rpe_rot_median_deg": frame_rotation.get_statistic(stats.median),
        "rpe_rot_max_deg": frame_rotation.get_statistic(stats.max),
    }
    return result


def assert_matches(ours: dict, reference: dict) -> None:
    assert ours["pairs"] == reference["pairs"]
    for key, value in reference.items():
        assert ours[key] == pytest.approx(value, abs=EVO_TOLERANCE), key


# --- against evo ------------------------------------------------------------------------------


def test_ate_and_frame_to_frame_error_match_evo_with_dropped_frames():
    estimate, groundtruth = make_pair(drop=True)
    ours = metrics.evaluate(estimate, groundtruth).as_dict()
    reference = evo_errors(evo_trajectory(groundtruth), evo_trajectory(estimate), drift=False)
    assert 190 < reference["pairs"] < 241  # dropped and unmatched poses are really left out
    assert reference["ate_rmse"] > 0.01  # drift: alignment has something to do
    assert_matches(ours, reference)


def test_all_metrics_including_drift_match_evo_on_uniform_timestamps():
    estimate, groundtruth = make_pair(drop=False, seed=4)
    ours = metrics.evaluate(estimate, groundtruth).as_dict()
    reference = evo_errors(evo_trajectory(groundtruth), evo_trajectory(estimate), drift=True)
    assert reference["pairs"] == 241
    assert_matches(ours, reference)


# --- closed forms and properties --------------------------------------------------------------


def test_interval_pairs_on_irregular_timestamps():
    # Hand-worked: 0 -> 1.0 nearest 1.05; 0.4 -> 1.4 nearest 1.5; 0.9 -> 1.9 nearest 2.2 (0.3 vs
    # 0.4); 1.05 -> 2.05 nearest 2.2; 1.5 -> 2.5 nearest 2.2; 2.2 -> 3.2 nearest is 2.2 itself
    # (gap to 5.0): no pair; 5.0 -> 6.0 beyond the end: no pair.
    first, second = metrics.interval_pairs(np.array([0.0, 0.4, 0.9, 1.05, 1.5, 2.2, 5.0]), 1.0)
    assert list(zip(first.tolist(), second.tolist(), strict=True)) == [
        (0, 3),
        (1, 4),
        (2, 5),
        (3, 5),
        (4, 5),
    ]


def test_constant_velocity_error_gives_drift_in_metres_per_second():
    # Estimate = ground truth plus a world-frame offset v t: every E_i is a pure translation of
    # length |v| (t_j - t_i), so the drift is |v| m/s and the frame-to-frame error |v| / 20.
    times = np.arange(61) / 20.0  # 20 Hz, 3 s
    truth = smooth_pose(times, seed=2)
    velocity = np.array([0.03, -0.04, 0.0])  # |v| = 0.05 m/s
    estimate = truth.copy()
    estimate[:, :3, 3] += velocity * times[:, None]
    errors = metrics.evaluate(Trajectory(times, estimate), Trajectory(times, truth))
    assert errors.drift_rmse_m_per_s == pytest.approx(0.05, abs=1e-12)
    assert errors.rpe_trans_median == pytest.approx(0.05 / 20, abs=1e-12)
    assert errors.rpe_trans_max == pytest.approx(0.05 / 20, abs=1e-12)
    assert errors.rpe_rot_max_deg == pytest.approx(0.0, abs=1e-9)
    assert errors.pairs == 61


def test_metrics_ignore_the_estimate_world_frame():
    estimate, groundtruth = make_pair(drop=True, seed=1)
    moved = Trajectory(
        estimate.timestamps, se3.exp(np.array([2.0, 0.1, -1.0, 5.0, -3.0, 1.0])) @ estimate.poses
    )
    before = metrics.evaluate(estimate, groundtruth).as_dict()
    after = metrics.evaluate(moved, groundtruth).as_dict()
    for key in KEYS:
        assert after[key] == pytest.approx(before[key], abs=1e-9), key


def test_perfect_estimate_has_zero_error_and_ate_removes_a_rigid_offset():
    times = 1.0 + np.arange(90) / 30.0
    truth = smooth_pose(times, seed=3)
    offset = se3.exp(np.array([0.0, 0.0, 1.0, 0.5, 0.5, 0.5]))
    errors = metrics.evaluate(Trajectory(times, offset @ truth), Trajectory(times, truth))
    values = errors.as_dict()
    assert values["pairs"] == 90
    for key in KEYS - {"pairs"}:
        assert values[key] == pytest.approx(0.0, abs=1e-9), key


def test_short_trajectory_has_no_drift():
    times = np.arange(10) / 30.0
    truth = smooth_pose(times)
    errors = metrics.evaluate(Trajectory(times, truth), Trajectory(times, truth))
    assert errors.drift_rmse_m_per_s is None
    assert "n/a" in errors.summary()


def test_too_few_associated_poses_is_a_clear_error():
    truth = Trajectory(np.arange(5) / 30.0, smooth_pose(np.arange(5) / 30.0))
    far = Trajectory(truth.timestamps + 10.0, truth.poses)
    with pytest.raises(metrics.MetricsError) as excinfo:
        metrics.evaluate(far, truth)
    assert "only 0 of 5" in str(excinfo.value) and "\n" not in str(excinfo.value)


def test_rotation_angles_are_precise_at_small_and_large_angles():
    for angle in (1e-9, 1e-4, 1.0, np.pi - 1e-6):
        axis = np.array([1.0, 2.0, -2.0]) / 3.0
        rotation = se3.exp(np.concatenate([angle * axis, np.zeros(3)]))[:3, :3]
        assert metrics.rotation_angles(rotation[None])[0] == pytest.approx(angle, rel=1e-7)


# --- ranking score (eq. 16) -------------------------------------------------------------------


def test_ranking_scores_hand_computed():
    errors = {
        "A": {"d1": 1.0, "d2": 2.0},
        "B": {"d1": 3.0, "d2": 2.0},
        "C": {"d1": 4.0, "d2": 6.0},
    }
    # Column sums d1 = 8, d2 = 10:
    # A = (1/8 + 2/10) / 2, B = (3/8 + 2/10) / 2, C = (4/8 + 6/10) / 2.
    scores = metrics.ranking_scores(errors)
    assert scores == pytest.approx({"A": 0.1625, "B": 0.2875, "C": 0.55}, abs=1e-15)
    assert sum(scores.values()) == pytest.approx(1.0)


def test_ranking_scores_need_every_dataset():
    with pytest.raises(metrics.MetricsError) as excinfo:
        metrics.ranking_scores({"A": {"d1": 1.0, "d2": 1.0}, "B": {"d1": 1.0}})
    assert "'B'" in str(excinfo.value) and "d2" in str(excinfo.value)


# --- the command ------------------------------------------------------------------------------


def test_evaluate_command_json_matches_evo_reading_the_same_files(tmp_path, capsys):
    estimate, groundtruth = make_pair(drop=False, seed=5)
    write_trajectory(tmp_path / "est.txt", estimate)
    write_trajectory(tmp_path / "gt.txt", groundtruth)
    assert main(["evaluate", str(tmp_path / "est.txt"), str(tmp_path / "gt.txt"), "--json"]) == 0
    printed = json.loads(capsys.readouterr().out)
    assert set(printed) == KEYS
    reference = evo_errors(
        file_interface.read_tum_trajectory_file(str(tmp_path / "gt.txt")),
        file_interface.read_tum_trajectory_file(str(tmp_path / "est.txt")),
        drift=True,
    )
    assert_matches(printed, reference)


def test_evaluate_command_text_and_error(tmp_path, capsys):
    estimate, groundtruth = make_pair(drop=False, seed=6)
    write_trajectory(tmp_path / "est.txt", estimate)
    write_trajectory(tmp_path / "gt.txt", groundtruth)
    assert main(["evaluate", str(tmp_path / "est.txt"), str(tmp_path / "gt.txt")]) == 0
    text = capsys.readouterr().out
    expected = metrics.evaluate(estimate, groundtruth)
    assert f"rmse {expected.ate_rmse:.4f} m" in text and "associated poses : 241" in text

    far = Trajectory(groundtruth.timestamps + 100.0, groundtruth.poses)
    write_trajectory(tmp_path / "far.txt", far)
    assert main(["evaluate", str(tmp_path / "far.txt"), str(tmp_path / "gt.txt")]) == 2
    error = capsys.readouterr().err
    assert error.startswith("kintinuous: error: only 0 of 241") and error.count("\n") == 1
