"""How much better could the pose graph place the keyframes if it knew where the odometry erred?

Takes a finished `reconstruct --loop-closure` run on a sequence with ground truth, rebuilds its
pose graph offline (keyframes chosen by the same rule on the uncorrected trajectory, odometry
edges between them, the run's loops with their true relative poses) and solves it three ways,
each frame then following its keyframe's correction as in the run:

- the run's rule: every odometry edge with the same standard deviations (config.loop_closure);
- an oracle: each odometry edge with its own true error as its standard deviation (translation
  and rotation), as if the tracker's uncertainty were known exactly up to direction;
- a directional oracle: each odometry edge with the covariance e e^T + diag(1 mm, 0.02 degrees)^2
  of its own true error e (rotation, translation), as if a tracker's full covariance knew in
  which direction it erred;
- every keyframe at its true pose (the floor of the frames-follow-keyframes scheme).

    python benchmarks/pose_graph_oracle.py DATASET RUN_FOLDER

prints the ATE RMSE of each (docs/loop_closure.md).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from kintinuous_ref import metrics, se3
from kintinuous_ref.config import LoopClosureConfig
from kintinuous_ref.datasets import tum
from kintinuous_ref.loop_closure import pose_graph
from kintinuous_ref.loop_closure.keyframes import is_new_keyframe


def keyframes(poses: np.ndarray, config: LoopClosureConfig) -> list[int]:
    """The frames the keyframe rule picks along `poses`."""
    chosen: list[int] = []
    for frame, pose in enumerate(poses):
        if is_new_keyframe(poses[chosen[-1]] if chosen else None, pose, config):
            chosen.append(frame)
    return chosen


def error_vectors(estimate: np.ndarray, truth: np.ndarray, frames: list[int]) -> np.ndarray:
    """(K - 1, 6) each odometry edge's true error [rotation vector, translation] in the pose
    graph's residual convention (docs of kintinuous_ref.loop_closure.pose_graph)."""
    rows = []
    for first, second in zip(frames, frames[1:], strict=False):
        measured = pose_graph.relative_pose(estimate[first], estimate[second])
        error = se3.inverse(measured) @ pose_graph.relative_pose(truth[first], truth[second])
        rows.append(np.hstack([se3.rotation_log(error[:3, :3]), error[:3, 3]]))
    return np.array(rows)


def sigma_covariance(translation: float, rotation: float) -> np.ndarray:
    """The diagonal covariance of standard deviations `translation` (m) and `rotation` (rad)."""
    return np.diag([rotation**2] * 3 + [translation**2] * 3)


def error_sigmas(errors: np.ndarray) -> list[np.ndarray]:
    """Each edge with the size of its own error (translation, rotation) as its sigmas."""
    return [sigma_covariance(max(np.linalg.norm(e[3:]), 1e-4), max(np.linalg.norm(e[:3]), 1e-5))
            for e in errors]  # fmt: skip


def directional_covariances(errors: np.ndarray) -> list[np.ndarray]:
    """Each edge with its own error vector e as its direction: e e^T + (1 mm, 0.02 degrees)^2."""
    floor = sigma_covariance(0.001, np.radians(0.02))
    return [np.outer(e, e) + floor for e in errors]


def solve_graph(estimate, truth, frames, loops, covariances, config) -> np.ndarray:  # noqa: ANN001
    """Keyframe poses that the pose graph puts out with one 6 x 6 covariance per odometry edge."""
    graph = pose_graph.PoseGraph()
    for frame in frames:
        graph.add_node(estimate[frame])
    for node, covariance in enumerate(covariances, start=1):
        measured = pose_graph.relative_pose(estimate[frames[node - 1]], estimate[frames[node]])
        graph.add_edge(node - 1, node, measured, 1.0, 1.0, covariance=covariance)
    for old, new in loops:
        measured = pose_graph.relative_pose(truth[old], truth[new])
        graph.add_edge(frames.index(old), frames.index(new), measured,
                       config.loop_sigma_translation, np.radians(config.loop_sigma_rotation_deg),
                       loop=True)  # fmt: skip
    solution = pose_graph.optimise(
        graph, config.switch_prior_sigma, consistency_sigmas=config.loop_consistency_sigmas
    )
    return solution.poses


def follow_keyframes(estimate: np.ndarray, frames: list[int], placed: np.ndarray) -> np.ndarray:
    """Every frame moved by its latest keyframe's correction."""
    latest = np.searchsorted(frames, np.arange(len(estimate)), side="right") - 1
    corrections = [placed[k] @ se3.inverse(estimate[frames[k]]) for k in range(len(frames))]
    return np.array([corrections[k] @ pose for k, pose in zip(latest, estimate, strict=True)])


def ate_mm(poses: np.ndarray, truth: np.ndarray) -> float:
    stamps = np.arange(len(poses), dtype=np.float64)
    errors = metrics.absolute_trajectory_errors(
        tum.Trajectory(stamps, poses), tum.Trajectory(stamps, truth[: len(poses)])
    )
    return 1000.0 * float(np.sqrt(np.mean(errors**2)))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("dataset", type=Path, help="the sequence (a TUM folder with ground truth)")
    parser.add_argument("run", type=Path, help="the output folder of a --loop-closure run")
    args = parser.parse_args()
    config = LoopClosureConfig()
    truth = tum.open_sequence(args.dataset).groundtruth_for_frames().poses
    estimate = tum.read_trajectory(args.run / "trajectory_uncorrected.txt").poses
    closures = json.loads((args.run / "report.json").read_text())["loop_closures"]["closures"]
    frames = keyframes(estimate, config)
    loops = [tuple(c["keyframe_frames"]) for c in closures]
    loops = [(old, new) for old, new in loops if old in frames and new in frames]
    rule = sigma_covariance(
        config.odometry_sigma_translation, np.radians(config.odometry_sigma_rotation_deg)
    )
    uniform = [rule] * (len(frames) - 1)
    errors = error_vectors(estimate, truth, frames)
    print(f"{len(frames)} keyframes, {len(loops)} loops")
    print(f"uncorrected                     ATE {ate_mm(estimate, truth):7.2f} mm")
    for label, covariances in (
        ("the same sigma on every edge", uniform),
        ("oracle sigma per edge", error_sigmas(errors)),
        ("oracle covariance per edge", directional_covariances(errors)),
    ):
        placed = solve_graph(estimate, truth, frames, loops, covariances, config)
        print(
            f"{label:31s} ATE {ate_mm(follow_keyframes(estimate, frames, placed), truth):7.2f} mm"
        )
    true_keyframes = follow_keyframes(estimate, frames, truth[frames])
    print(f"{'every keyframe at its true pose':31s} ATE {ate_mm(true_keyframes, truth):7.2f} mm")


if __name__ == "__main__":
    main()
