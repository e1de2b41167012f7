"""Tracking over large motions: frames far apart in time, where FOVIS (paper V-A) should hold.

    .venv/bin/python benchmarks/large_motion.py                       # every case, every method
    .venv/bin/python benchmarks/large_motion.py --cases redkitchen/20 --methods fovis
    .venv/bin/python benchmarks/large_motion.py --json large_motion.jsonl
    .venv/bin/python benchmarks/large_motion.py --set fovis.switch_rule=vector
    .venv/bin/python benchmarks/large_motion.py --cases redkitchen/1 --methods fovis/icp+rgbd \
        --no-steps --set fovis.dense_from_fovis=true        # every frame, the dense half seeded

Cases: redkitchen frames 0-299 taken every 10th, 20th and 30th frame (0.33-1 s apart: 10-24 cm
and up to 20 degrees a step), and the first 10 s of the synthetic `loop` path rendered with
sensor noise and taken every 15th frame (2 Hz: 18-27 cm and up to 12 degrees a step). `desk/15`
and the like work too; the desk's orbit keeps looking at the table, so its images move little.

Each case runs the whole pipeline (kintinuous_ref.pipeline, moving volume, default
configuration) with `fovis`, `icp+rgbd` and `fovis/icp+rgbd` (the paper's switching) from the
first ground-truth pose, and prints the ATE RMSE (kintinuous_ref.metrics) and the tracking
failures of each; for a switching method (`fovis/X`) also, per step, the errors of FOVIS's and the
dense estimate's increments against the ground truth's, where the dense one started (`dense*`: from
FOVIS's increment, or the last good one where FOVIS failed), the two disagreements the rules
measure and which increment was used. Then, for FOVIS alone on each pair of consecutive frames: the
corners with depth in both frames, the mutually consistent matches, the consistency clique, the
inliers, the error against the ground truth's increment and, when it failed, why. Steps are named
by the recording's frame numbers. A case whose real data is absent is skipped.
"""

from __future__ import annotations

import argparse
import copy
import json
import sys
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from kintinuous_ref import metrics, pipeline, se3
from kintinuous_ref.backend import load_backend
from kintinuous_ref.camera import Intrinsics
from kintinuous_ref.config import Config
from kintinuous_ref.datasets import real_dataset, tum
from kintinuous_ref.datasets.synthetic import make_scenario
from kintinuous_ref.odometry import TrackingResult, fovis
from kintinuous_ref.preprocess import preprocess_frame
from kintinuous_ref.program.config_options import configured

CASES = ("redkitchen/10", "redkitchen/20", "redkitchen/30", "loop/15")
METHODS = ("fovis", "icp+rgbd", "fovis/icp+rgbd")
REDKITCHEN_FRAMES = 300  # the shared recording's frames 0-299
SYNTHETIC_FRAMES = 300  # 10 s of the synthetic path at 30 Hz


@dataclass
class Case:
    name: str
    camera: Intrinsics
    frames: list[tum.Frame]  # index = position in the case, into `truth`
    truth: tum.Trajectory
    numbers: list[int]  # each frame's number in the recording


def load_case(name: str) -> Case | None:
    """`scene/stride`: every stride-th frame of the scene; None when its data is absent."""
    scene, _, stride_text = name.partition("/")
    stride = int(stride_text or 1)
    if scene == "redkitchen":
        folder = real_dataset("redkitchen")
        if folder is None:
            return None
        sequence = tum.open_sequence(folder)
        truth = sequence.groundtruth_for_frames()
        indices = range(0, min(REDKITCHEN_FRAMES, len(sequence)), stride)
        images = ((sequence[i].colour, sequence[i].depth) for i in indices)
        camera = sequence.camera
    else:
        scenario = make_scenario(scene, frames=SYNTHETIC_FRAMES, noise=True)
        truth, camera = scenario.trajectory, scenario.camera
        indices = range(0, SYNTHETIC_FRAMES, stride)
        images = (scenario.render(i) for i in indices)
    frames = [
        tum.Frame(position, float(truth.timestamps[index]), colour, depth)
        for position, (index, (colour, depth)) in enumerate(zip(indices, images, strict=True))
    ]
    kept = list(indices)
    return Case(
        name, camera, frames, tum.Trajectory(truth.timestamps[kept], truth.poses[kept]), kept
    )


class RecordingTracker:
    """A tracker that keeps every TrackingResult it returns (the pipeline keeps only poses)."""

    def __init__(self, tracker: object) -> None:
        self.tracker = tracker
        self.results: list[TrackingResult] = []
        self.model_stride = getattr(tracker, "model_stride", 1)

    def track(self, *arguments: object) -> TrackingResult:
        result = self.tracker.track(*arguments)
        self.results.append(result)
        return result


class RecordingOdometry:
    """A backend's odometry stage whose make_tracker hands out RecordingTrackers."""

    def __init__(self, odometry: object) -> None:
        self.odometry = odometry
        self.trackers: list[RecordingTracker] = []

    def __getattr__(self, name: str) -> object:
        return getattr(self.odometry, name)

    def make_tracker(self, *arguments: object) -> RecordingTracker:
        tracker = RecordingTracker(self.odometry.make_tracker(*arguments))
        self.trackers.append(tracker)
        return tracker


def run_method(case: Case, method: str, backend_name: str, config: Config) -> dict:
    """The pipeline with `method` on the case: ATE RMSE (m), failures and their reasons, and
    for a switching method each step's decision (switch_steps)."""
    backend = copy.copy(load_backend(backend_name))
    backend.odometry = recording = RecordingOdometry(backend.odometry)
    result = pipeline.run(
        iter(case.frames),
        case.camera,
        config,
        odometry=method,
        groundtruth=case.truth,
        backend=backend,
    )
    estimate = tum.Trajectory(np.array(result.timestamps), np.array(result.poses))
    errors = metrics.evaluate(estimate, case.truth)
    row = {
        "case": case.name,
        "method": method,
        "frames": len(result.poses),
        "ate_rmse_m": errors.ate_rmse,
        "failures": result.tracking_failures,
        "failure_reasons": result.failure_reasons,
    }
    if "/" in method:
        row["switch_steps"] = list(switch_steps(case, recording.trackers[0].results))
    return row


def increment_error(estimate: np.ndarray | None, truth: np.ndarray) -> list[float] | None:
    """[translation error (m), rotation error (deg)] of an increment; None for no estimate."""
    if estimate is None:
        return None
    error = se3.inverse(truth) @ estimate
    return [
        float(np.linalg.norm(error[:3, 3])),
        float(np.degrees(se3.rotation_angle(error[:3, :3]))),
    ]


def switch_steps(case: Case, results: list[TrackingResult]) -> Iterator[dict]:
    """Per step of a switching tracker: both increments' errors, the dense start, the length
    and vector disagreements (m) and the estimator used."""
    poses = case.truth.poses
    for index, result in enumerate(results, start=1):
        decision = result.switch
        if decision is None:  # a stale frame: the dense half was not asked
            continue
        truth = se3.inverse(poses[index - 1]) @ poses[index]
        fovis_t = None if decision.fovis_increment is None else decision.fovis_increment[:3, 3]
        dense_t = None if decision.dense_increment is None else decision.dense_increment[:3, 3]
        both = fovis_t is not None and dense_t is not None
        yield {
            "pair": case.numbers[index - 1 : index + 1],
            "true_step_m": float(np.linalg.norm(truth[:3, 3])),
            "true_turn_deg": float(np.degrees(se3.rotation_angle(truth[:3, :3]))),
            "fovis_error": increment_error(decision.fovis_increment, truth),
            "dense_error": increment_error(decision.dense_increment, truth),
            "seeded": not np.array_equal(decision.dense_start, np.eye(4)),
            "length_gap_m": (
                abs(float(np.linalg.norm(fovis_t)) - float(np.linalg.norm(dense_t)))
                if both
                else None
            ),
            "vector_gap_m": float(np.linalg.norm(fovis_t - dense_t)) if both else None,
            "used": result.used or "failed",
        }


def print_switch_step(step: dict) -> None:
    def error(value: list[float] | None) -> str:
        return (
            "      failed      "
            if value is None
            else f"{value[0] * 1000:6.1f} mm {value[1]:4.1f} deg"
        )

    def gap(value: float | None) -> str:
        return "   -  " if value is None else f"{value * 1000:5.1f}"

    first, second = step["pair"]
    print(
        f"  {first:3d}->{second:3d}  step {step['true_step_m'] * 100:5.1f} cm "
        f"{step['true_turn_deg']:5.1f} deg  fovis {error(step['fovis_error'])}  "
        f"dense{'*' if step['seeded'] else ' '} {error(step['dense_error'])}  "
        f"gaps (mm) length {gap(step['length_gap_m'])} vector {gap(step['vector_gap_m'])}  "
        f"used {step['used']}",
        flush=True,
    )


def fovis_steps(case: Case) -> Iterator[dict]:
    """FOVIS on each consecutive pair: what each step kept and the error of its increment."""
    config = Config()
    previous = None
    for frame in case.frames:
        current = preprocess_frame(frame.colour, frame.depth, case.camera, config.preprocess)
        if previous is not None:
            result = fovis.estimate_motion(previous, current, case.camera, config.fovis)
            poses = case.truth.poses
            truth = se3.inverse(poses[frame.index - 1]) @ poses[frame.index]
            error = se3.inverse(truth) @ result.increment
            yield {
                "case": case.name,
                "pair": case.numbers[frame.index - 1 : frame.index + 1],
                "true_step_m": float(np.linalg.norm(truth[:3, 3])),
                "true_turn_deg": float(np.degrees(se3.rotation_angle(truth[:3, :3]))),
                "features": [result.previous_features, result.current_features],
                "matches": result.matches,
                "clique": result.clique,
                "inliers": result.inliers,
                "ok": result.ok,
                "error_m": float(np.linalg.norm(error[:3, 3])) if result.ok else None,
                "error_deg": (
                    float(np.degrees(se3.rotation_angle(error[:3, :3]))) if result.ok else None
                ),
                "reason": result.reason,
            }
        previous = current


def print_step(step: dict) -> None:
    error = (
        f"{step['error_m'] * 1000:6.1f} mm {step['error_deg']:5.2f} deg"
        if step["ok"]
        else f"failed: {step['reason']}"
    )
    first, second = step["pair"]
    print(
        f"  {first:3d}->{second:3d}  step {step['true_step_m'] * 100:5.1f} cm "
        f"{step['true_turn_deg']:5.1f} deg  features {step['features'][0]:4d}/"
        f"{step['features'][1]:4d}  matches {step['matches']:4d}  clique {step['clique']:4d}  "
        f"inliers {step['inliers']:4d}  {error}",
        flush=True,
    )


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--cases", nargs="+", default=list(CASES), help="scene/stride")
    parser.add_argument("--methods", nargs="+", default=list(METHODS))
    parser.add_argument("--backend", default="auto", help="ref, cpu, cuda or auto")
    parser.add_argument("--no-steps", action="store_true", help="skip FOVIS's per-pair table")
    parser.add_argument("--json", type=Path, help="append the rows to this JSON-lines file")
    parser.add_argument(
        "--set", action="append", default=[], metavar="KEY=VALUE", help="a setting, repeatable"
    )
    args = parser.parse_args(argv)
    config = configured(Config(), None, args.set)
    rows = []
    for name in args.cases:
        case = load_case(name)
        if case is None:
            print(f"{name}: data absent, skipped")
            continue
        print(f"{name}: {len(case.frames)} frames")
        for method in args.methods:
            row = run_method(case, method, args.backend, config)
            rows.append(row)
            print(
                f"  {method:16s} ATE RMSE {row['ate_rmse_m'] * 1000:7.1f} mm  "
                f"failures {row['failures']:3d} of {row['frames'] - 1}",
                flush=True,
            )
            if "switch_steps" in row and not args.no_steps:
                for step in row["switch_steps"]:
                    print_switch_step(step)
        if not args.no_steps:
            steps = list(fovis_steps(case))
            for step in steps:
                print_step(step)
            failed = sum(not step["ok"] for step in steps)
            print(f"  FOVIS alone failed on {failed} of {len(steps)} pairs")
            rows.extend(steps)
    if args.json:
        with args.json.open("a") as out:
            for row in rows:
                out.write(json.dumps(row) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
