"""Tracking accuracy of every odometry method: ATE RMSE on synthetic scenes and real data.

    .venv/bin/python benchmarks/accuracy.py                          # the whole grid (hours!)
    .venv/bin/python benchmarks/accuracy.py --scenes desk --methods icp icp+rgbd --frames 100
    .venv/bin/python benchmarks/accuracy.py --scenes redkitchen --size 320x240

Each run is the Kintinuous loop reduced to what tracking needs: preprocess -> track (against the
previous frame and the model raycast from the previous pose) -> fuse the frame when tracking
succeeded -> raycast the model for the next frame. The volume does not move (the sequences here stay
inside it); the first pose is the ground truth's. Prints one row per (scene, method): ATE RMSE,
tracking failures, seconds per frame of tracking and in all. `--json FILE` keeps the rows.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import cv2
import numpy as np

from kintinuous_ref import metrics, preprocess, raycast, tsdf
from kintinuous_ref.config import Config, with_overrides
from kintinuous_ref.datasets import data_folder, tum
from kintinuous_ref.odometry import METHODS, make_tracker

REAL_DATA = data_folder()  # $KINTINUOUS_DATA, else ../shared/data beside the repository
SYNTHETIC = ("desk", "corridor", "dark")


def frames_of(scene: str, count: int, width: int, height: int, noise: bool):
    """(camera, ground truth Trajectory, iterator of (colour, depth)) of a scene."""
    if scene in SYNTHETIC or scene in ("floor", "loop"):
        from kintinuous_ref.datasets import synthetic

        scenario = synthetic.make_scenario(scene, count, width, height, seed=0, noise=noise)
        images = (scenario.render(i) for i in range(count))
        return scenario.camera, scenario.trajectory, images
    sequence = tum.open_sequence(REAL_DATA / scene)
    camera = sequence.camera
    resize = (width, height) != (camera.width, camera.height)
    if resize:
        camera = camera.resized(width, height)

    def images():
        for frame in sequence.frames(0, count):
            colour, depth = frame.colour, frame.depth
            if resize:
                colour = cv2.resize(colour, (width, height), interpolation=cv2.INTER_AREA)
                depth = cv2.resize(depth, (width, height), interpolation=cv2.INTER_NEAREST)
            yield colour, depth

    truth = sequence.groundtruth
    return camera, tum.Trajectory(sequence.timestamps[:count], truth.poses[:count]), images()


def run(scene: str, method: str, count: int, width: int, height: int, config: Config) -> dict:
    camera, truth, images = frames_of(scene, count, width, height, noise=True)
    tracker = make_tracker(method, config, camera)
    poses, failures, reasons = [], 0, []
    previous = model = volume = None
    track_seconds, start = 0.0, time.perf_counter()
    for index, (colour, depth) in enumerate(images):
        colour = np.clip(np.asarray(colour), 0, 255).astype(np.uint8)
        current = preprocess.preprocess_frame(colour, depth, camera, config.preprocess)
        if index == 0:
            pose, ok = truth.poses[0].copy(), True
            volume = tsdf.make_volume(config.volume, pose)
        else:
            tick = time.perf_counter()
            result = tracker.track(previous, current, model, poses[-1])
            track_seconds += time.perf_counter() - tick
            pose, ok = result.pose, result.ok
            if not ok:
                failures += 1
                reasons.append(f"{index}: {result.reason}")
        if ok:
            tsdf.integrate(volume, current.depth, pose, camera)
        model = raycast.raycast(volume, pose, camera)
        poses.append(pose)
        previous = current
    estimate = tum.Trajectory(truth.timestamps[: len(poses)], np.array(poses))
    errors = metrics.evaluate(estimate, tum.Trajectory(truth.timestamps, truth.poses))
    frames = len(poses)
    return {
        "scene": scene,
        "method": method,
        "frames": frames,
        "size": f"{width}x{height}",
        "ate_rmse_m": errors.as_dict()["ate_rmse"],
        "failures": failures,
        "track_s_per_frame": track_seconds / max(1, frames - 1),
        "total_s_per_frame": (time.perf_counter() - start) / frames,
        "first_failures": reasons[:5],
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--scenes", nargs="+", default=[*SYNTHETIC, "redkitchen"])
    parser.add_argument("--methods", nargs="+", default=list(METHODS), choices=METHODS)
    parser.add_argument("--frames", type=int, default=300)
    parser.add_argument("--size", default="320x240", help="WIDTHxHEIGHT (images are resized)")
    parser.add_argument("--set", nargs="*", default=[], help="config overrides key=value (JSON)")
    parser.add_argument("--json", type=Path, help="append the rows to this JSON-lines file")
    args = parser.parse_args(argv)
    width, height = (int(v) for v in args.size.split("x"))
    overrides = {}
    for item in args.set:
        key, _, value = item.partition("=")
        try:
            overrides[key] = json.loads(value)
        except json.JSONDecodeError:
            overrides[key] = value
    config = with_overrides(Config(), overrides)
    print(
        f"{'scene':12s} {'method':16s} {'frames':>6s} {'ATE RMSE':>10s} {'fails':>6s} "
        f"{'track s/f':>9s} {'all s/f':>8s}"
    )
    for scene in args.scenes:
        for method in args.methods:
            row = run(scene, method, args.frames, width, height, config)
            print(
                f"{scene:12s} {method:16s} {row['frames']:6d} {row['ate_rmse_m']:10.4f} "
                f"{row['failures']:6d} {row['track_s_per_frame']:9.2f} "
                f"{row['total_s_per_frame']:8.2f}",
                flush=True,
            )
            if args.json:
                with args.json.open("a") as out:
                    out.write(json.dumps({**row, "overrides": overrides}) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
