"""`kintinuous benchmark`: per-stage milliseconds and frames per second of the whole pipeline on
one backend (the paper's Tables V and VI report the same per-stage times at 640x480).

The kernels are prepared as `reconstruct` prepares them (a compile is announced on stderr and
its time kept for the next estimate), then a warm-up run over the first two frames (every stage
at the dataset's size, the tracker included), then the timed run. Its first frame is left out of the
statistics (it has no model to track against); every later frame runs every stage, the raycast
included.
"""

from __future__ import annotations

import os
import platform
import subprocess
import sys
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from kintinuous_ref.config import Config
from kintinuous_ref.errors import ConfigError
from kintinuous_ref.signals import Interrupted

DEFAULT_FRAMES = 30


def timing_stats(values: list[float]) -> dict[str, float | None]:
    """{mean, median, max} of milliseconds (None where nothing was timed)."""
    if not values:
        return {"mean": None, "median": None, "max": None}
    return {
        "mean": float(np.mean(values)),
        "median": float(np.median(values)),
        "max": float(np.max(values)),
    }


TRAFFIC_FIELDS = ("launches", "host_waits", "bytes_to_host", "graph_replays")


def traffic_stats(frames: list[Any]) -> dict[str, float]:
    """The median over `frames` (DeviceTraffic, one per frame) of each of TRAFFIC_FIELDS
    (zeros where nothing was counted)."""
    return {
        name: float(np.median([getattr(frame, name) for frame in frames])) if frames else 0.0
        for name in TRAFFIC_FIELDS
    }


def benchmark(
    dataset: str | None,
    backend: str = "auto",
    odometry: str = "icp+rgbd",
    frames: int = DEFAULT_FRAMES,
    config: Config | None = None,
    start: int = 0,
    synchronize_stages: bool = False,
) -> dict[str, Any]:
    """Run the pipeline over `frames` frames of `dataset` (a TUM folder or scenario name) on
    `backend` and return {backend, dataset, odometry, frames, resolution, timing_ms: {stage:
    {mean, median, max}}, fps (1000 / median total ms), the device traffic per frame
    (launches_per_frame, host_waits_per_frame, bytes_to_host_per_frame,
    graph_replays_per_frame: medians, zeros without a device) and per stage
    (traffic_per_stage), stages_synchronized} over frames 2..N. `synchronize_stages`: each
    stage's time includes its device work (pipeline.run's), at the price of a wait per stage;
    without, a GPU's stage times are the host's and its work shows in whichever stage waits
    next, while frames/s is right either way."""
    from kintinuous_ref import pipeline
    from kintinuous_ref.backend import load_backend
    from kintinuous_ref.program.reconstruct import (
        check_pyramid,
        check_start,
        open_dataset,
        prepare_kernels,
    )

    if frames < 2:
        raise ConfigError(f"--frames must be at least 2 (the first is a warm-up), got {frames}")
    config = config or Config()
    chosen = load_backend(backend)
    sequence = open_dataset(dataset, frames_needed=start + frames)
    check_start(start, sequence)
    check_pyramid(config, sequence.camera.width, sequence.camera.height, odometry)
    groundtruth = None
    if sequence.groundtruth is not None:
        groundtruth = sequence.groundtruth_for_frames()
    count = frames_to_time(frames, start, len(sequence))
    prepare_kernels(chosen, config, odometry)  # a compile announced, and its time kept
    for length in (min(2, count), count):  # the warm-up, then the timed run
        result = pipeline.run(
            sequence.frames(start, length),
            sequence.camera,
            config,
            odometry,
            groundtruth,
            backend=chosen,
            predict_model=True,
            synchronize_stages=synchronize_stages,
        )
        if result.interrupted:  # a table of the frames before the signal would pass for the whole
            raise Interrupted(
                result.signal_name,
                f"{result.reason} after {result.frames} of {length} frames: no timings printed",
            )
    timing = {stage: timing_stats(values[1:]) for stage, values in result.timings_ms.items()}
    total = timing.get("total", {}).get("median")
    traffic = {stage: traffic_stats(frames[1:]) for stage, frames in result.traffic.items()}
    return {
        "backend": chosen.name,
        "dataset": str(sequence.path),
        "odometry": odometry,
        "frames": result.frames,
        "timed_frames": max(result.frames - 1, 0),
        "resolution": config.volume.resolution,
        "image": [sequence.camera.width, sequence.camera.height],
        "tracking_failures": result.tracking_failures,
        # finest to coarsest; (0, ...) with --fast-odometry
        "icp_iterations": list(config.icp.iterations),
        "timing_ms": timing,
        "fps": (1000.0 / total) if total else None,
        **{f"{name}_per_frame": traffic["total"][name] for name in TRAFFIC_FIELDS},
        "traffic_per_stage": traffic,
        "stages_synchronized": synchronize_stages,
    }


def frames_to_time(frames: int, start: int, length: int) -> int:
    """The frames a benchmark of `frames` from `start` runs on a sequence of `length`: fewer
    than asked is said in one line on stderr, so that the table's "timed frames" is not the
    only sign; fewer than 2 (a warm-up and one timed frame) is refused (ConfigError)."""
    count = min(frames, length - start)
    if count < 2:
        raise ConfigError(
            f"--start {start} leaves {count} frame of the sequence's {length} (frames "
            f"0..{length - 1}); a benchmark needs at least 2 (the first is a warm-up): choose "
            f"--start at most {length - 2}"
        )
    if count < frames:
        print(
            f"kintinuous: warning: --frames {frames} from --start {start}: the sequence ends at "
            f"frame {length - 1}, so {count} frames run ({count - 1} timed)",
            file=sys.stderr,
            flush=True,
        )
    return count


def format_table(report: dict[str, Any]) -> str:
    """The report as a small text table (stage, mean, median, max ms; frames/s)."""
    width, height = report["image"]
    lines = [
        f"{report['backend']} backend, {report['odometry']}, {width}x{height}, "
        f"{report['resolution']}^3, {report['timed_frames']} timed frames, ICP iterations "
        f"{'/'.join(str(n) for n in report['icp_iterations'])} (finest to coarsest)",
        f"{'stage':12s} {'mean ms':>9s} {'median ms':>10s} {'max ms':>9s}",
    ]
    for stage, stats in report["timing_ms"].items():
        if stats["median"] is None:
            lines.append(f"{stage:12s} {'-':>9s} {'-':>10s} {'-':>9s}")
        else:
            lines.append(
                f"{stage:12s} {stats['mean']:9.1f} {stats['median']:10.1f} {stats['max']:9.1f}"
            )
    fps = report["fps"]
    lines.append(f"frames/s (median): {fps:.2f}" if fps else "frames/s: -")
    if report["stages_synchronized"]:
        lines.append("each stage waited for its device work (--sync-stages)")
    if report["launches_per_frame"]:
        lines.append(
            f"device per frame (median): {report['launches_per_frame']:.0f} kernel launches, "
            f"{report['host_waits_per_frame']:.0f} host waits, "
            f"{report['bytes_to_host_per_frame']:.0f} bytes to the host"
            + (
                f", {report['graph_replays_per_frame']:.0f} graph replays"
                if report["graph_replays_per_frame"]
                else ""
            )
        )
    return "\n".join(lines)


def machine_line() -> str:
    """CPU model, CPUs and numba threads: a timing means little without them."""
    try:
        described = subprocess.run(["lscpu"], capture_output=True, text=True, check=True).stdout
        model = next(
            line.split(":", 1)[1].strip()
            for line in described.splitlines()
            if line.startswith("Model name")
        )
    except (OSError, subprocess.CalledProcessError, StopIteration):
        model = platform.processor() or platform.machine()
    try:
        import numba

        threads = str(numba.get_num_threads())
    except ImportError:
        threads = "none (numba not installed)"
    return f"{model}, {os.cpu_count()} CPUs, numba threads: {threads}"


def timed(function: Callable[[], Any], repeats: int = 7) -> np.ndarray:
    """Seconds of `repeats` runs, after one untimed run (which compiles or loads the kernels)."""
    function()
    times = np.empty(repeats)
    for repeat in range(repeats):
        started = time.perf_counter()
        function()
        times[repeat] = time.perf_counter() - started
    return times


def speed_line(name: str, reference: np.ndarray, fast: np.ndarray) -> str:
    """One line comparing two sets of timings in seconds (`timed`): medians and interquartile
    ranges [25th-75th percentile] in ms, and the range of the speed-up of `fast` (the cpu
    backend) over `reference`."""
    r25, r50, r75 = 1000 * np.percentile(reference, [25, 50, 75])
    f25, f50, f75 = 1000 * np.percentile(fast, [25, 50, 75])
    return (
        f"{name}: reference {r50:.1f} ms [{r25:.1f}-{r75:.1f}], fast (cpu) {f50:.1f} ms "
        f"[{f25:.1f}-{f75:.1f}], speed-up {r50 / f50:.1f}x [{r25 / f75:.1f}-{r75 / f25:.1f}]"
    )
