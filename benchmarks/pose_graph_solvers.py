"""The pose graph solved by scipy (loop_closure/pose_graph.py) and by gtsam, if installed.

    python benchmarks/pose_graph_solvers.py [--nodes 100 300]

A circle of keyframes with noisy odometry (drift), true loops every tenth node back to the first
lap, and one false loop across the circle. Prints, per solver: seconds, position RMSE against
the truth, and whether the false loop bent the map (its largest position error).
gtsam (Levenberg-Marquardt, loop edges with its DCS robust model: the same switchable-constraint
cost in closed form) is optional: `pip install gtsam`.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from kintinuous_ref import se3
from kintinuous_ref.loop_closure import pose_graph


def problem(count: int, seed: int = 0) -> tuple[np.ndarray, list[np.ndarray], list[tuple]]:
    """(true poses, odometry poses, loops (i, j, measurement, false?))."""
    rng = np.random.default_rng(seed)
    laps = 2
    truth = []
    for i in range(count):
        angle = 2 * np.pi * laps * i / count
        pose = se3.exp(np.array([0.0, 0.0, angle, 0, 0, 0]))
        pose[:3, 3] = [3 * np.cos(angle), 3 * np.sin(angle), 0.05 * np.sin(5 * angle)]
        truth.append(pose)
    truth = np.array(truth)
    odometry = [truth[0]]
    for i in range(1, count):
        step = pose_graph.relative_pose(truth[i - 1], truth[i])
        noise = se3.exp(np.concatenate([rng.normal(0, 0.001, 3), rng.normal(0, 0.005, 3)]))
        odometry.append(odometry[-1] @ step @ noise)
    lap = count // laps
    loops = [(i, i + lap, pose_graph.relative_pose(truth[i], truth[i + lap]), False)
             for i in range(0, lap, 10)]  # fmt: skip
    loops.append((lap // 4, lap + 3 * lap // 4, np.eye(4), True))
    return truth, odometry, loops


def solve_scipy(odometry: list[np.ndarray], loops: list[tuple]) -> np.ndarray:
    graph = pose_graph.PoseGraph()
    for pose in odometry:
        graph.add_node(pose)
    for i in range(1, len(odometry)):
        graph.add_edge(i - 1, i, pose_graph.relative_pose(odometry[i - 1], odometry[i]),
                       0.01, 0.003)  # fmt: skip
    for i, j, measurement, _ in loops:
        graph.add_edge(i, j, measurement, 0.01, 0.003, loop=True)
    return pose_graph.optimise(graph).poses


def solve_gtsam(odometry: list[np.ndarray], loops: list[tuple]) -> np.ndarray:
    import gtsam

    graph = gtsam.NonlinearFactorGraph()
    # gtsam's Pose3 tangent is [rotation, translation], as the project's twists.
    sigmas = np.array([0.003] * 3 + [0.01] * 3)
    odometry_noise = gtsam.noiseModel.Diagonal.Sigmas(sigmas)
    loop_noise = gtsam.noiseModel.Robust.Create(
        gtsam.noiseModel.mEstimator.DCS.Create(1.0), gtsam.noiseModel.Diagonal.Sigmas(sigmas)
    )
    graph.add(gtsam.PriorFactorPose3(0, gtsam.Pose3(odometry[0]),
                                     gtsam.noiseModel.Constrained.All(6)))  # fmt: skip
    initial = gtsam.Values()
    for i, pose in enumerate(odometry):
        initial.insert(i, gtsam.Pose3(pose))
        if i:
            measured = pose_graph.relative_pose(odometry[i - 1], pose)
            graph.add(gtsam.BetweenFactorPose3(i - 1, i, gtsam.Pose3(measured), odometry_noise))
    for i, j, measurement, _ in loops:
        graph.add(gtsam.BetweenFactorPose3(i, j, gtsam.Pose3(measurement), loop_noise))
    result = gtsam.LevenbergMarquardtOptimizer(graph, initial).optimize()
    return np.array([result.atPose3(i).matrix() for i in range(len(odometry))])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--nodes", type=int, nargs="+", default=[50, 100])
    args = parser.parse_args()
    solvers = {"scipy": solve_scipy}
    try:
        import gtsam  # noqa: F401

        solvers["gtsam"] = solve_gtsam
    except ImportError:
        print("gtsam is not installed: scipy only")
    for count in args.nodes:
        truth, odometry, loops = problem(count)
        drift = np.linalg.norm(np.array(odometry)[:, :3, 3] - truth[:, :3, 3], axis=1)
        print(
            f"{count} nodes, {len(loops)} loops (1 false): odometry max error {drift.max():.3f} m"
        )
        for name, solve in solvers.items():
            start = time.perf_counter()
            poses = solve(odometry, loops)
            seconds = time.perf_counter() - start
            error = np.linalg.norm(poses[:, :3, 3] - truth[:, :3, 3], axis=1)
            print(f"  {name:6s} {seconds:7.3f} s   position rmse {np.sqrt(np.mean(error**2)):.4f} m"
                  f"   max {error.max():.4f} m")  # fmt: skip


if __name__ == "__main__":
    main()
