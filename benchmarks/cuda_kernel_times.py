"""Where a frame's GPU time goes on the cuda backend: every kernel launch of `kintinuous
benchmark` timed by a pair of CUDA events around it, summed per kernel and per frame.

    python benchmarks/cuda_kernel_times.py DATASET [--frames 40] [--set K=V] [--json F]

Launches go one by one (graphs off), each between two events on the default stream. The GPU
would reach the first event as soon as the host records it and then wait out numba's dispatch
of the kernel (tens of microseconds), so a one-thread kernel that spins for about 0.3 ms goes
first: by the time the GPU reaches the event, the kernel is queued behind it, and the time
between the events is the kernel's own.
Prints per kernel its calls and milliseconds per frame and microseconds per call, most time
first, and per stage (the package the kernel lives in) the GPU milliseconds per frame: the
floor under a frame once the host is out of it. Needs a GPU (numba's simulator has no events
that time anything).
"""

from __future__ import annotations

import argparse
import json
from collections import defaultdict
from pathlib import Path
from typing import Any

import numpy as np
from numba import cuda

from kintinuous_fast.targets import cuda as cuda_target
from kintinuous_fast.targets import cuda_graphs
from kintinuous_ref.config import Config, with_overrides
from kintinuous_ref.program.benchmark import benchmark

# Steps of the spinning kernel: a chain of dependent multiply-adds, about 0.3 ms on an H100
# (each step waits for the one before), longer than the host takes to dispatch a launch.
HOLD_STEPS = 100_000


@cuda.jit
def _hold(scratch, steps):
    value = scratch[0]
    for _ in range(steps):
        value = value * 0.999999 + 1e-6
    scratch[0] = value


class KernelTimer:
    """Wraps targets.cuda.CountedKernel's launch: events before and after each launch, the
    pairs read once the run is over (reading one waits for the GPU)."""

    def __init__(self) -> None:
        self.pairs: list[tuple[str, Any, Any]] = []
        self.active = False
        self._launch = cuda_target.CountedKernel.__getitem__
        self.scratch = cuda.to_device(np.zeros(1, dtype=np.float32))

    def install(self) -> None:
        timer, original = self, self._launch

        def timed(kernel: Any, configuration: Any) -> Any:
            launch = original(kernel, configuration)
            if not timer.active:
                return launch

            def between_events(*arguments: Any) -> None:
                before, after = cuda.event(), cuda.event()
                _hold[1, 1](timer.scratch, HOLD_STEPS)
                before.record()
                launch(*arguments)
                after.record()
                timer.pairs.append((kernel_name(kernel), before, after))

            return between_events

        cuda_target.CountedKernel.__getitem__ = timed

    def milliseconds(self) -> dict[str, list[float]]:
        cuda.synchronize()
        times: dict[str, list[float]] = defaultdict(list)
        for name, before, after in self.pairs:
            times[name].append(before.elapsed_time(after))
        return times


def kernel_name(kernel: Any) -> str:
    """stage.function of a kernel: the package under kintinuous_fast and the Python name."""
    function = kernel.dispatcher.py_func
    package = function.__module__.split(".")
    stage = package[1] if package[0] == "kintinuous_fast" and len(package) > 1 else package[0]
    return f"{stage}.{function.__name__}"


def report(times: dict[str, list[float]], frames: int) -> dict[str, Any]:
    """Per kernel {calls, ms} per frame and us per call; per stage GPU ms per frame."""
    kernels = {
        name: {
            "calls_per_frame": len(values) / frames,
            "ms_per_frame": sum(values) / frames,
            "us_per_call": 1000.0 * sum(values) / len(values),
        }
        for name, values in times.items()
    }
    stages: dict[str, float] = defaultdict(float)
    for name, row in kernels.items():
        stages[name.split(".")[0]] += row["ms_per_frame"]
    stages["total"] = sum(stages.values())
    return {"frames": frames, "kernels": kernels, "stages_gpu_ms_per_frame": dict(stages)}


def print_report(result: dict[str, Any], top: int) -> None:
    rows = sorted(result["kernels"].items(), key=lambda item: -item[1]["ms_per_frame"])
    print(f"{'kernel':44s} {'calls/frame':>11s} {'ms/frame':>9s} {'us/call':>8s}")
    for name, row in rows[:top]:
        calls, ms, us = row["calls_per_frame"], row["ms_per_frame"], row["us_per_call"]
        print(f"{name:44s} {calls:11.1f} {ms:9.3f} {us:8.1f}")
    stages = result["stages_gpu_ms_per_frame"]
    print("GPU ms per frame by stage: " + ", ".join(f"{k} {v:.3f}" for k, v in stages.items()))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("dataset", help="TUM folder or synthetic scenario name")
    parser.add_argument("--frames", type=int, default=40)
    parser.add_argument("--odometry", default="icp+rgbd")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    parser.add_argument("--top", type=int, default=30, help="kernels listed")
    parser.add_argument("--json", type=Path, help="write the report here")
    args = parser.parse_args()
    overrides = {key: json.loads(value) for key, _, value in (s.partition("=") for s in args.set)}
    run = dict(backend="cuda", odometry=args.odometry, config=with_overrides(Config(), overrides))
    cuda_graphs.enable(False)
    timer = KernelTimer()
    timer.install()
    benchmark(args.dataset, frames=2, **run)  # compiles every kernel, untimed
    timer.active = True
    benchmark(args.dataset, frames=args.frames, **run)
    # the timed call runs its own two warm-up frames first: every launch of both counts
    result = report(timer.milliseconds(), args.frames + 2)
    print_report(result, args.top)
    if args.json:
        args.json.write_text(json.dumps(result, indent=1))


if __name__ == "__main__":
    main()
