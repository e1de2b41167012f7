"""Trajectory accuracy as the paper reports it (section VII), in the notation of Sturm et al. 2012.

Sturm, Engelhard, Endres, Burgard, Cremers, "A Benchmark for the Evaluation of RGB-D SLAM
Systems", IROS 2012. P_1..P_n are the estimated poses, Q_1..Q_n the ground truth (camera-to-world),
after associating the two trajectories by timestamp.

- Absolute trajectory error (ATE, Sturm eq. 4-5, paper Table I): the positions of P are aligned
  to those of Q by the rigid motion S that minimises the squared distances (Horn 1987; Umeyama
  1991 without scale); F_i = Q_i^-1 S P_i and the error is ||trans(F_i)||.
- Relative pose error (Sturm eq. 1-2): E_i = (Q_i^-1 Q_j)^-1 (P_i^-1 P_j).
  Frame to frame (paper Tables II, III): j = i + 1 in the associated list; the translation
  ||trans(E_i)|| in metres and the rotation angle of E_i in degrees.
  Drift (paper Table IV): j = the pose closest in time to t_i + 1 s; the RMSE of ||trans(E_i)||,
  metres per second.
- Ranking score (paper eq. 16) of m algorithms over n datasets.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from kintinuous_ref.datasets.tum import MAX_TIME_DIFFERENCE, Trajectory, associate
from kintinuous_ref.errors import KintinuousError

# Timestamps in TUM files have 1e-6 s resolution: t_i + 1 s may miss the last stamp by that much.
_TIMESTAMP_RESOLUTION = 1e-6


class MetricsError(KintinuousError):
    """Trajectories that cannot be compared (too few associated poses, empty error tables)."""


@dataclass(frozen=True)
class TrajectoryErrors:
    """The numbers of the paper's Tables I-IV for one trajectory (metres, degrees, m/s)."""

    ate_rmse: float
    ate_median: float
    ate_max: float
    rpe_trans_median: float
    rpe_trans_max: float
    rpe_rot_median_deg: float
    rpe_rot_max_deg: float
    drift_rmse_m_per_s: float | None  # None when the trajectory spans less than the interval
    pairs: int  # number of associated poses

    def as_dict(self) -> dict[str, float | int | None]:
        return asdict(self)

    def summary(self) -> str:
        drift = (
            "n/a (trajectory shorter than 1 s)"
            if self.drift_rmse_m_per_s is None
            else f"{self.drift_rmse_m_per_s:.4f} m/s (RMSE over 1 s)"
        )
        return "\n".join(
            [
                f"associated poses : {self.pairs}",
                f"ATE              : rmse {self.ate_rmse:.4f} m, median {self.ate_median:.4f} m,"
                f" max {self.ate_max:.4f} m",
                f"frame-to-frame   : translation median {self.rpe_trans_median:.4f} m,"
                f" max {self.rpe_trans_max:.4f} m",
                f"                   rotation median {self.rpe_rot_median_deg:.4f} deg,"
                f" max {self.rpe_rot_max_deg:.4f} deg",
                f"drift            : {drift}",
            ]
        )


def associate_trajectories(
    estimate: Trajectory, groundtruth: Trajectory, max_difference: float = MAX_TIME_DIFFERENCE
) -> tuple[Trajectory, Trajectory]:
    """The estimated and ground-truth poses paired one-to-one by nearest timestamp (within
    max_difference, as TUM's associate.py), in order of the estimate's timestamps."""
    est_indices, gt_indices = associate(estimate.timestamps, groundtruth.timestamps, max_difference)
    return (
        Trajectory(estimate.timestamps[est_indices], estimate.poses[est_indices]),
        Trajectory(groundtruth.timestamps[gt_indices], groundtruth.poses[gt_indices]),
    )


def align_rigid(source: np.ndarray, target: np.ndarray) -> np.ndarray:
    """The rigid motion S (4x4) minimising sum ||target_i - S source_i||^2 over points (N, 3).

    Umeyama 1991 (eq. 38-41) with the scale fixed to 1: SVD of the cross-covariance, with the
    sign of the last singular direction chosen so that S is a rotation, never a reflection.
    """
    source_mean, target_mean = source.mean(axis=0), target.mean(axis=0)
    covariance = (target - target_mean).T @ (source - source_mean) / len(source)
    u, _, vt = np.linalg.svd(covariance)
    sign = np.eye(3)
    sign[2, 2] = np.sign(np.linalg.det(u) * np.linalg.det(vt)) or 1.0
    rotation = u @ sign @ vt
    motion = np.eye(4)
    motion[:3, :3] = rotation
    motion[:3, 3] = target_mean - rotation @ source_mean
    return motion


def absolute_trajectory_errors(estimate: Trajectory, groundtruth: Trajectory) -> np.ndarray:
    """||trans(Q_i^-1 S P_i)|| = ||q_i - S p_i|| per associated pose (Sturm eq. 4), metres."""
    alignment = align_rigid(estimate.positions, groundtruth.positions)
    aligned = estimate.positions @ alignment[:3, :3].T + alignment[:3, 3]
    return np.linalg.norm(groundtruth.positions - aligned, axis=1)


def relative_pose_errors(
    estimate: np.ndarray, groundtruth: np.ndarray, first: np.ndarray, second: np.ndarray
) -> np.ndarray:
    """E_k = (Q_i^-1 Q_j)^-1 (P_i^-1 P_j) for pairs (i, j) = (first[k], second[k]) (Sturm eq. 1)."""
    estimated_motion = _relative(estimate[first], estimate[second])
    true_motion = _relative(groundtruth[first], groundtruth[second])
    return _relative(true_motion, estimated_motion)


def interval_pairs(timestamps: np.ndarray, interval: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """Pairs (i, j) with j the pose closest in time to t_i + interval.

    Only poses i whose t_i + interval lies within the trajectory's span take part, so that no
    pair is cut short at the end. Timestamps must be sorted.
    """
    timestamps = np.asarray(timestamps, dtype=np.float64)
    targets = timestamps + interval
    first = np.flatnonzero(targets <= timestamps[-1] + _TIMESTAMP_RESOLUTION)
    targets = targets[first]
    right = np.clip(np.searchsorted(timestamps, targets), 0, len(timestamps) - 1)
    left = np.clip(right - 1, 0, len(timestamps) - 1)
    take_left = targets - timestamps[left] <= timestamps[right] - targets
    second = np.where(take_left, left, right)
    # Across a gap longer than 2 intervals the closest pose may be i itself: no motion to compare.
    keep = second > first
    return first[keep], second[keep]


def rotation_angles(rotations: np.ndarray) -> np.ndarray:
    """Rotation angle (radians, in [0, pi]) of each rotation matrix (..., 3, 3).

    atan2 of the antisymmetric and the symmetric parts keeps full precision at small angles,
    where arccos((trace - 1) / 2) loses half of the digits.
    """
    antisymmetric = np.stack(
        [
            rotations[..., 2, 1] - rotations[..., 1, 2],
            rotations[..., 0, 2] - rotations[..., 2, 0],
            rotations[..., 1, 0] - rotations[..., 0, 1],
        ],
        axis=-1,
    )
    cosine = (np.trace(rotations, axis1=-2, axis2=-1) - 1.0) / 2.0
    return np.arctan2(np.linalg.norm(antisymmetric, axis=-1) / 2.0, cosine)


def evaluate(
    estimate: Trajectory,
    groundtruth: Trajectory,
    max_difference: float = MAX_TIME_DIFFERENCE,
    drift_interval: float = 1.0,
) -> TrajectoryErrors:
    """ATE, frame-to-frame error and drift of an estimated trajectory (paper Tables I-IV)."""
    est, gt = associate_trajectories(estimate, groundtruth, max_difference)
    if len(est) < 2:
        raise MetricsError(
            f"only {len(est)} of {len(estimate)} estimated poses have a ground-truth pose within "
            f"{max_difference} s; at least 2 are needed (do the timestamps match?)"
        )
    ate = absolute_trajectory_errors(est, gt)

    consecutive = np.arange(len(est) - 1)
    frame_errors = relative_pose_errors(est.poses, gt.poses, consecutive, consecutive + 1)
    frame_translation = np.linalg.norm(frame_errors[:, :3, 3], axis=1)
    frame_rotation = np.degrees(rotation_angles(frame_errors[:, :3, :3]))

    first, second = interval_pairs(est.timestamps, drift_interval)
    drift = None
    if len(first):
        drift_errors = relative_pose_errors(est.poses, gt.poses, first, second)
        # The translation error accumulated over `drift_interval` seconds, per second.
        drift_translation = np.linalg.norm(drift_errors[:, :3, 3], axis=1) / drift_interval
        drift = float(np.sqrt(np.mean(drift_translation**2)))

    return TrajectoryErrors(
        ate_rmse=float(np.sqrt(np.mean(ate**2))),
        ate_median=float(np.median(ate)),
        ate_max=float(np.max(ate)),
        rpe_trans_median=float(np.median(frame_translation)),
        rpe_trans_max=float(np.max(frame_translation)),
        rpe_rot_median_deg=float(np.median(frame_rotation)),
        rpe_rot_max_deg=float(np.max(frame_rotation)),
        drift_rmse_m_per_s=drift,
        pairs=len(est),
    )


def ranking_scores(errors: dict[str, dict[str, float]]) -> dict[str, float]:
    """Paper eq. 16: S(A_i, A, D) = (1/n) sum_j E(A_i, D_j) / sum_k E(A_k, D_j).

    errors[algorithm][dataset] is one error measure (e.g. maximum translation error); every
    algorithm needs a value for every dataset. Each dataset contributes the algorithm's share of
    the summed error, so a lower score is better and the scores add up to 1.
    """
    if not errors:
        raise MetricsError("ranking needs at least one algorithm")
    datasets = set(next(iter(errors.values())))
    for algorithm, per_dataset in errors.items():
        if set(per_dataset) != datasets:
            missing = sorted(datasets.symmetric_difference(per_dataset))
            raise MetricsError(f"algorithm {algorithm!r}: no error value for dataset(s) {missing}")
    if not datasets:
        raise MetricsError("ranking needs at least one dataset")
    totals = {dataset: sum(per[dataset] for per in errors.values()) for dataset in datasets}
    zero = sorted(dataset for dataset, total in totals.items() if not total > 0)
    if zero:
        raise MetricsError(f"dataset(s) {zero}: errors sum to zero, no share can be computed")
    return {
        algorithm: sum(per[dataset] / totals[dataset] for dataset in datasets) / len(datasets)
        for algorithm, per in errors.items()
    }


def _relative(first: np.ndarray, second: np.ndarray) -> np.ndarray:
    """first^-1 second for stacks of rigid motions (K, 4, 4), using R^T rather than inv()."""
    rotation_t = np.swapaxes(first[:, :3, :3], 1, 2)
    result = np.zeros(np.broadcast_shapes(first.shape, second.shape))
    result[:, :3, :3] = rotation_t @ second[:, :3, :3]
    result[:, :3, 3] = np.einsum("kab,kb->ka", rotation_t, second[:, :3, 3] - first[:, :3, 3])
    result[:, 3, 3] = 1.0
    return result
