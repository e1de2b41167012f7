"""Dense odometry speed, reference (NumPy) vs kintinuous_fast cpu (numba), and what the "fast
odometry" setting (skip the finest pyramid level) costs in accuracy.

    .venv/bin/python benchmarks/odometry_speed.py                     # redkitchen, 640x480
    .venv/bin/python benchmarks/odometry_speed.py --scene desk --frames 100 --speed-frames 6

1. Speed: per-call milliseconds of `tracker.track` (icp, rgbd, icp+rgbd) and of one ICP / RGB-D
   system at the finest level, median over frames 2..N after a warm-up frame, on identical
   preprocessed frames (kintinuous_fast.preprocess.cpu) for both backends.
2. Accuracy: ATE RMSE over --frames frames of icp+rgbd with the cpu backend, default iterations
   (10/5/4) vs fast_odometry (0/5/4), first pose from the ground truth.

The model ICP tracks against is a stand-in for the TSDF raycast (which costs seconds per frame
at 640x480 in the reference): the previous frame's vertex and normal maps, moved into the world by
the previous ESTIMATED pose - i.e. frame-to-frame ICP, so drift accumulates as in odometry.
"""

from __future__ import annotations

import argparse
import sys
import time

import numpy as np

from kintinuous_fast import load_backend
from kintinuous_fast.odometry import cpu as cpu_odometry
from kintinuous_fast.odometry.icp import cpu as cpu_icp
from kintinuous_fast.odometry.rgbd import cpu as cpu_rgbd
from kintinuous_fast.preprocess import cpu as cpu_preprocess
from kintinuous_ref import metrics
from kintinuous_ref.config import Config, fast_odometry
from kintinuous_ref.datasets import data_folder, tum
from kintinuous_ref.odometry import icp as ref_icp
from kintinuous_ref.odometry import rgbd as ref_rgbd

REAL_DATA = data_folder()  # $KINTINUOUS_DATA, else ../shared/data beside the repository


class Model:
    """The fields of raycast.ModelPrediction the trackers read."""

    def __init__(self, frame, pose: np.ndarray) -> None:  # noqa: ANN001
        level = frame.levels[0]
        rotation, translation = pose[:3, :3].astype(np.float32), pose[:3, 3].astype(np.float32)
        self.pose = pose
        self.vertices = level.vertices @ rotation.T + translation
        self.normals = level.normals @ rotation.T


def frames_of(scene: str, count: int):
    """(camera, ground truth Trajectory, iterator of (colour, depth)) at 640x480."""
    if scene == "redkitchen" and (REAL_DATA / scene).exists():
        sequence = tum.open_sequence(REAL_DATA / scene)
        truth = sequence.groundtruth
        images = ((f.colour, f.depth) for f in sequence.frames(0, count))
        return (
            sequence.camera,
            tum.Trajectory(truth.timestamps[:count], truth.poses[:count]),
            images,
        )
    from kintinuous_ref.datasets import synthetic

    scenario = synthetic.make_scenario("desk" if scene == "redkitchen" else scene, count)
    images = (scenario.render(i) for i in range(count))
    return scenario.camera, scenario.trajectory, images


def milliseconds(function, *args) -> tuple[float, object]:  # noqa: ANN001
    start = time.perf_counter()
    result = function(*args)
    return 1000 * (time.perf_counter() - start), result


def speed(scene: str, count: int, config: Config) -> dict[str, tuple[float, float]]:
    """name -> (median ref ms, median cpu ms) over frames 2..count-1 (frame 1 warms up)."""
    camera, truth, images = frames_of(scene, count)
    frames = [cpu_preprocess.preprocess_frame(c, d, camera, config.preprocess) for c, d in images]
    timings: dict[str, list[tuple[float, float]]] = {}
    trackers = {
        method: (
            load_backend("ref").odometry.make_tracker(method, config, camera),
            load_backend("cpu").odometry.make_tracker(method, config, camera),
        )
        for method in ("icp", "rgbd", "icp+rgbd")
    }
    for index in range(1, len(frames)):
        previous, current = frames[index - 1], frames[index]
        pose = truth.poses[index - 1]
        model = Model(previous, pose)
        level = current.levels[0]
        icp_args = (
            level.vertices,
            level.normals,
            pose,
            model.vertices,
            model.normals,
            pose,
            camera,
        )
        prepare = (level.depth, level.intensity, level.intensity_dx, level.intensity_dy, camera)
        ref_points = ref_rgbd.prepare_level(*prepare, config.rgbd.min_gradient[0], 6.0)
        cpu_points = cpu_rgbd.prepare_level(*prepare, config.rgbd.min_gradient[0], 6.0)
        prev = previous.levels[0]
        rgbd_args = (pose, pose, prev.depth, prev.intensity, camera)
        samples = {
            "icp_system (level 0)": (
                milliseconds(ref_icp.icp_system, *icp_args)[0],
                milliseconds(cpu_icp.icp_system, *icp_args)[0],
            ),
            "rgbd_system (level 0)": (
                milliseconds(ref_rgbd.rgbd_system, ref_points, *rgbd_args)[0],
                milliseconds(cpu_rgbd.rgbd_system, cpu_points, *rgbd_args)[0],
            ),
        }
        for method, (ref_tracker, cpu_tracker) in trackers.items():
            ref_ms, ref_result = milliseconds(ref_tracker.track, previous, current, model, pose)
            cpu_ms, cpu_result = milliseconds(cpu_tracker.track, previous, current, model, pose)
            difference = np.linalg.norm(ref_result.pose[:3, 3] - cpu_result.pose[:3, 3])
            assert difference < 1e-4, f"{method}: ref and cpu poses differ by {difference} m"
            samples[f"track {method}"] = (ref_ms, cpu_ms)
        if index > 1:  # frame 1 compiles / warms caches
            for name, pair in samples.items():
                timings.setdefault(name, []).append(pair)
    return {name: tuple(np.median(np.array(v), axis=0)) for name, v in timings.items()}


def accuracy(scene: str, count: int, config: Config) -> dict[str, tuple[float, float, int]]:
    """setting -> (ATE RMSE m, ms per track call, failures) of icp+rgbd on the cpu backend."""
    camera, truth, images = frames_of(scene, count)
    settings = {"default (10/5/4)": config, "fast odometry (0/5/4)": fast_odometry(config)}
    trackers = {
        name: cpu_odometry.make_tracker("icp+rgbd", c, camera) for name, c in settings.items()
    }
    poses = {name: [truth.poses[0].copy()] for name in settings}
    seconds = dict.fromkeys(settings, 0.0)
    failures = dict.fromkeys(settings, 0)
    previous = None
    for index, (colour, depth) in enumerate(images):
        current = cpu_preprocess.preprocess_frame(colour, depth, camera, config.preprocess)
        if previous is not None:
            for name, tracker in trackers.items():
                model = Model(previous, poses[name][-1])
                start = time.perf_counter()
                result = tracker.track(previous, current, model, poses[name][-1])
                seconds[name] += time.perf_counter() - start
                failures[name] += not result.ok
                poses[name].append(result.pose)
        previous = current
        print(f"\r  frame {index + 1}/{count}", end="", file=sys.stderr, flush=True)
    print(file=sys.stderr)
    rows = {}
    for name, estimate in poses.items():
        trajectory = tum.Trajectory(truth.timestamps[: len(estimate)], np.array(estimate))
        ate = metrics.absolute_trajectory_errors(trajectory, truth)
        rows[name] = (
            float(np.sqrt(np.mean(ate**2))),
            1000 * seconds[name] / (len(estimate) - 1),
            failures[name],
        )
    return rows


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--scene", default="redkitchen", help="redkitchen (real) or a synthetic")
    parser.add_argument("--speed-frames", type=int, default=6)
    parser.add_argument("--frames", type=int, default=100, help="frames for the ATE comparison")
    args = parser.parse_args(argv)
    config = Config()
    if args.speed_frames > 2:
        print(f"speed, {args.scene} 640x480, median of frames 2..{args.speed_frames - 1}")
        print(f"{'call':24s} {'ref ms':>9s} {'cpu ms':>9s} {'speed-up':>8s}")
        for name, (ref_ms, cpu_ms) in speed(args.scene, args.speed_frames, config).items():
            print(f"{name:24s} {ref_ms:9.1f} {cpu_ms:9.1f} {ref_ms / cpu_ms:8.1f}", flush=True)
    if args.frames > 1:
        print(
            f"\naccuracy, icp+rgbd on the cpu backend, {args.scene} 640x480, {args.frames} frames"
        )
        print(f"{'setting':24s} {'ATE RMSE m':>10s} {'ms/track':>9s} {'failures':>8s}")
        for name, (ate, ms, fails) in accuracy(args.scene, args.frames, config).items():
            print(f"{name:24s} {ate:10.4f} {ms:9.1f} {fails:8d}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
