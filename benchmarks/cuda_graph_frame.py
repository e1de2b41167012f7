"""One dense estimate on a GPU, launched by Python and replayed as a captured CUDA graph.

The cuda backend runs a frame's ICP+RGB-D estimate as a fixed sequence of kernels
(kintinuous_fast/odometry/frame_on_device.py) and waits once for its record. Each launch through
numba's dispatcher costs tens of microseconds of host time, so a frame's ~90 launches cost
milliseconds however fast the kernels are. The same launches made on a stream can be captured as
a CUDA graph (cuda.bindings.driver: cuStreamBeginCapture, the launches, cuStreamEndCapture,
cuGraphInstantiate) and replayed with one cuGraphLaunch. This script measures both on one pair
of real frames, checks that the replayed record equals the launched one, and prints the medians.

    python benchmarks/cuda_graph_frame.py TUM_FOLDER [--start 0] [--repeats 50] [--json OUT]

Needs a CUDA GPU (numba-cuda with cuda.bindings). The report has the largest difference between
the two records' pose entries: not zero in general, as the RGB-D pair list is filled by atomics
and its sums come in another order each run.
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from pathlib import Path

import numpy as np


def frames_and_model(folder: str, start: int) -> tuple:
    """(tracker, previous frame, current frame, model prediction) on the device: two frames of
    the folder preprocessed, the first fused at its pose and raycast as the second's model."""
    from kintinuous_ref.backend import load_backend
    from kintinuous_ref.config import Config
    from kintinuous_ref.program.reconstruct import open_dataset

    backend, config = load_backend("cuda"), Config()
    sequence = open_dataset(folder, frames_needed=start + 2)
    camera = sequence.camera
    first, second = sequence.frames(start, 2)
    prepared = [
        backend.preprocess.preprocess_frame(
            backend.upload(frame.colour), backend.upload(frame.depth), camera, config.preprocess
        )
        for frame in (first, second)
    ]
    pose = np.eye(4)
    volume = backend.tsdf.make_volume(config.volume, pose, config.colour.max_weight)
    weights = backend.colour.colour_weights(prepared[0], config.colour)
    backend.tsdf.integrate(volume, prepared[0].depth, pose, camera, prepared[0].colour, weights)
    tracker = backend.odometry.make_tracker("icp+rgbd", config, camera)
    model = backend.predict_surface(volume, pose, camera, stride=tracker.model_stride)
    return tracker, prepared[0], prepared[1], model


def median_ms(step, repeats: int) -> float:  # noqa: ANN001
    """The median wall time of `step()` in milliseconds (each call ends with a host wait)."""
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        step()
        times.append(1000.0 * (time.perf_counter() - start))
    return statistics.median(times)


def captured(frame) -> object:  # noqa: ANN001
    """The frame's launches captured on its stream as an instantiated graph."""
    from cuda.bindings import driver

    handle = frame.stream.handle
    stream = driver.CUstream(int(handle.value if hasattr(handle, "value") else handle))
    mode = driver.CUstreamCaptureMode.CU_STREAM_CAPTURE_MODE_RELAXED
    (error,) = driver.cuStreamBeginCapture(stream, mode)
    assert error == driver.CUresult.CUDA_SUCCESS, error
    frame.launch()
    error, graph = driver.cuStreamEndCapture(stream)
    assert error == driver.CUresult.CUDA_SUCCESS, error
    error, executable = driver.cuGraphInstantiate(graph, 0)
    assert error == driver.CUresult.CUDA_SUCCESS, error
    return lambda: driver.cuGraphLaunch(executable, stream)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("folder", help="a TUM RGB-D folder")
    parser.add_argument("--start", type=int, default=0)
    parser.add_argument("--repeats", type=int, default=50)
    parser.add_argument("--json", type=Path, help="write the numbers here too")
    args = parser.parse_args()
    from numba import cuda

    from kintinuous_fast.odometry.frame_on_device import POSE, FrameOnDevice
    from kintinuous_fast.targets import TRAFFIC

    tracker, previous, current, model = frames_and_model(args.folder, args.start)
    pose = np.eye(4)
    problem = tracker.problem(previous, current, model, pose)
    launched = FrameOnDevice(tracker, problem, previous, current)
    want = launched.run(pose)  # compiles every kernel
    before = TRAFFIC.launches
    launched.run(pose)
    launches = TRAFFIC.launches - before
    dispatched_ms = median_ms(lambda: launched.run(pose), args.repeats)

    replayed = FrameOnDevice(tracker, problem, previous, current, stream=cuda.stream())
    replay = captured(replayed)

    def replay_frame() -> np.ndarray:
        replayed.upload(pose)
        replay()
        return replayed.record()

    got = replay_frame()
    difference = float(np.abs(got[POSE : POSE + 16] - want[POSE : POSE + 16]).max())
    replayed_ms = median_ms(replay_frame, args.repeats)
    name = cuda.get_current_device().name
    report = {
        "device": name.decode() if isinstance(name, bytes) else str(name),
        "image": list(current.levels[0].depth.shape[::-1]),
        "iterations": list(tracker.iterations),
        "launches_per_frame": launches,
        "dispatched_ms": dispatched_ms,
        "replayed_ms": replayed_ms,
        "speedup": dispatched_ms / replayed_ms,
        "max_pose_entry_difference": difference,
        "repeats": args.repeats,
    }
    print(json.dumps(report, indent=2))
    if args.json:
        args.json.write_text(json.dumps(report, indent=2))


if __name__ == "__main__":
    main()
