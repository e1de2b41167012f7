"""Where a warm pipeline spends its time: cProfile over `kintinuous benchmark` after a first run
has compiled every kernel, so compilation stays out of the profile (the first run's time is
printed apart). Only the frames after the first `--skip` of the timed run are profiled, and not
their reading from disk: the first frames of a run allocate its buffers and, on a GPU, launch
kernel by kernel and capture their graphs, which later frames replay.

    python benchmarks/warm_profile.py DATASET --backend cuda --frames 30 [--skip 6] [--set K=V]
        [--out F]
    python benchmarks/warm_profile.py DATASET --loops [--frames 30] [--json F]

Prints the stages' medians, the functions with the most time of their own and the project's
functions by cumulative time, per frame; `--out` keeps the profile for pstats or snakeviz.
`--loops` (cpu backend) runs without the profiler and times every parallel loop instead: its
wall time per frame (the other threads' hand-over included; the median over the frames the
stages' medians cover), per stage the time outside the loops, which is what the host's
Python costs, and the minor page faults of each frame's work (a frame whose arrays land on
fresh pages pays for each, in whatever loop first writes them); `--json` writes the same
numbers, with the thread count numba used, for benchmarks/thread_sweep.py.
"""

from __future__ import annotations

import argparse
import cProfile
import itertools
import json
import os
import pstats
import resource
import time
from collections import defaultdict
from collections.abc import Iterable, Iterator, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from kintinuous_ref.config import Config, with_overrides
from kintinuous_ref.program.benchmark import benchmark


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("dataset", help="TUM folder or synthetic scenario name")
    parser.add_argument("--backend", default="cpu")
    parser.add_argument("--odometry", default="icp+rgbd")
    parser.add_argument("--frames", type=int, default=30)
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    parser.add_argument("--top", type=int, default=25, help="rows of each listing")
    parser.add_argument("--skip", type=int, default=6, help="frames run before the profile")
    parser.add_argument("--out", type=Path, help="write the profile here")
    parser.add_argument("--loops", action="store_true", help="time each cpu loop, no profiler")
    parser.add_argument("--json", type=Path, help="with --loops: write the loop report here")
    args = parser.parse_args()
    if args.json and not args.loops:
        parser.error("--json writes the --loops report; add --loops")
    overrides = {key: json.loads(value) for key, _, value in (s.partition("=") for s in args.set)}
    config = with_overrides(Config(), overrides)
    run = dict(backend=args.backend, odometry=args.odometry, config=config)
    started = time.perf_counter()
    benchmark(args.dataset, frames=2, **run)
    print(f"first run (compiling or loading the kernels): {time.perf_counter() - started:.1f} s")
    if args.loops:
        report = time_loops(args.dataset, args.frames, run)
        print_loop_report(report)
        if args.json:
            args.json.write_text(json.dumps(report, indent=1) + "\n")
        return
    profiler = cProfile.Profile()
    result, frames = profile_steady_frames(profiler, args.dataset, args.frames, args.skip, run)
    medians = {stage: round(t["median"], 2) for stage, t in result["timing_ms"].items()}
    print(f"medians (ms), frames 2..{args.frames}, profiled from frame {args.skip}: {medians}")
    if not frames:
        parser.error(f"--skip {args.skip} leaves no frame of {args.frames} to profile")
    if args.out:
        profiler.dump_stats(args.out)
    stats = pstats.Stats(profiler)
    for order, restriction in (("tottime", ()), ("cumulative", ("kintinuous",))):
        print(f"\n{order}, ms per frame ({frames} frames), calls per frame:")
        stats.sort_stats(order)
        rows = [
            (key, stats.stats[key])
            for key in stats.fcn_list
            if all(word in key[0] for word in restriction)
        ][: args.top]
        for (file, line, name), (_, calls, own, cumulative, _) in rows:
            where = f"{Path(file).parent.name}/{Path(file).name}:{line}({name})"
            print(
                f"{1000 * own / frames:8.2f} {1000 * cumulative / frames:8.2f} "
                f"{calls / frames:8.1f}  {where}"
            )


def profile_steady_frames(
    profiler: cProfile.Profile, dataset: str, frames: int, skip: int, run: dict
) -> tuple[dict[str, Any], int]:
    """`benchmark` with `profiler` on from the frame after the first `skip` of each run until
    the run ends, off while a frame is read: (the benchmark's result, the frames profiled)."""
    from kintinuous_ref import pipeline

    unprofiled = pipeline.run
    profiled = [0]

    def steady(frames: Iterable[Any]) -> Iterator[Any]:
        iterator = iter(frames)
        for index in itertools.count():
            profiler.disable()
            try:
                frame = next(iterator)
            except StopIteration:
                return
            if index >= skip:
                profiled[0] += 1
                profiler.enable()
            yield frame

    def run_profiled(frames, *args, **options):  # noqa: ANN001, ANN002, ANN003, ANN202
        try:
            return unprofiled(steady(frames), *args, **options)
        finally:
            profiler.disable()

    pipeline.run = run_profiled
    try:
        result = benchmark(dataset, frames=frames, **run)
    finally:
        pipeline.run = unprofiled
    return result, profiled[0]


class LoopClock:
    """Seconds and calls of each loop, per frame: per-frame numbers give medians over the same
    frames as the stages' medians, which a busy machine's outliers leave alone."""

    def __init__(self) -> None:
        self.runs: list[list[dict[str, list[float]]]] = []
        self.faults: list[list[int]] = []  # per run, the minor page faults of each frame's work
        # the time between iterations of a level: (level, seconds), the last call's (level, end)
        self.between: list[tuple[int, float]] = []
        self.last_iteration: tuple[int, float] | None = None

    def frames(self, frames: Iterable[Any]) -> Iterator[Any]:
        """`frames`, opening a new record for each: the loops called until the pipeline asks
        for the next frame are that frame's."""
        self.runs.append([])
        self.faults.append([])
        for frame in frames:
            self.runs[-1].append(defaultdict(list))
            before = minor_faults()
            yield frame  # back here when the pipeline asks for the next frame
            self.faults[-1].append(minor_faults() - before)

    def iteration(self, level: int, started: float, ended: float) -> None:
        """Count a joint-loop call of `level` from `started` to `ended` (perf_counter): the
        time since the previous call of the same level is host time between iterations."""
        if self.last_iteration is not None and self.last_iteration[0] == level:
            self.between.append((level, started - self.last_iteration[1]))
        self.last_iteration = (level, ended)

    def add(self, name: str, seconds: float) -> None:
        """Count a call of loop `name` to the frame under way (none before the first frame)."""
        if self.runs and self.runs[-1]:
            self.runs[-1][-1][name].append(seconds)


def time_loops(dataset: str, frames: int, run: dict) -> dict[str, Any]:
    """Run the benchmark with every kintinuous_fast module's run_parallel timed (the cpu loops
    are called through it, but for a level of the joint loop whose steps run in one compiled
    call, JointLevel.refine, timed whole) and return loop_report's summary: timing the calls
    from outside the loops includes the other threads' hand-over, which is what a thread count
    changes."""
    import kintinuous_fast.odometry.icp.cpu_joint as joint
    import kintinuous_fast.targets.cpu_probe as probe
    from kintinuous_ref import pipeline

    unframed, unlevelled = pipeline.run, joint.JointLevel.system
    unrefined = joint.JointLevel.refine
    clock = LoopClock()
    level: list[int | None] = [None]  # the joint loop's level while its system is computed

    def timing(untimed):  # noqa: ANN001, ANN202
        def timed(loop, *args, **options):  # noqa: ANN001, ANN002, ANN003, ANN202
            started = time.perf_counter()
            untimed(loop, *args, **options)
            ended = time.perf_counter()
            name = probe.loop_name(loop)
            if loop is joint._joint_loop and level[0] is not None:
                name = f"{name} L{level[0]}"
                clock.iteration(level[0], started, ended)
            clock.add(name, ended - started)

        return timed

    def levelled(self, *args, **options):  # noqa: ANN001, ANN002, ANN003, ANN202
        level[0] = self.level
        try:
            return unlevelled(self, *args, **options)
        finally:
            level[0] = None

    def refined(self, *args, **options):  # noqa: ANN001, ANN002, ANN003, ANN202
        # A level whose steps all run in one compiled call: its time shared out over its steps,
        # as calls of its loop (each with its solve, a few microseconds); no host time between
        # them to count.
        started = time.perf_counter()
        result = unrefined(self, *args, **options)
        if result is not None:
            seconds = (time.perf_counter() - started) / max(self.steps, 1)
            for _ in range(self.steps):
                clock.add(f"odometry.{self.loop.__name__} L{self.level}", seconds)
        return result

    def framed(frames, *args, **options):  # noqa: ANN001, ANN002, ANN003, ANN202
        return unframed(clock.frames(frames), *args, **options)

    pipeline.run = framed
    joint.JointLevel.system = levelled
    joint.JointLevel.refine = refined
    try:
        with probe.run_parallel_replaced(timing):
            result = benchmark(dataset, frames=frames, **run)
    finally:
        pipeline.run = unframed
        joint.JointLevel.system = unlevelled
        joint.JointLevel.refine = unrefined
    medians = {stage: t["median"] for stage, t in result["timing_ms"].items()}
    # The benchmark's last run is the timed one; its first frame (no model) is left out, as
    # from the stages' statistics.
    report = loop_report(medians, clock.runs[-1][1:], clock.faults[-1][1:])
    report["between_iterations_us"] = {
        f"L{lv}": float(np.median([1e6 * s for at, s in clock.between if at == lv]))
        for lv in sorted({at for at, _ in clock.between})
    }
    return report


def loop_report(
    medians: dict[str, float], frames: list[dict[str, list[float]]], faults: Sequence[int] = ()
) -> dict[str, Any]:
    """Per loop, the median ms per frame and the mean calls per frame over `frames` (each a
    record of seconds per call per loop), each stage's median split into its loops and the time
    outside them (the host's Python), the page faults of the same frames (`fault_summary` of
    `faults`), and the thread count numba ran with, since NUMBA_NUM_THREADS above the machine's
    cores is not honoured as asked."""
    import numba

    names = {name for frame in frames for name in frame}
    ms = {name: [1000 * sum(frame.get(name, ())) for frame in frames] for name in names}
    loops = {
        name: {
            "ms_per_frame": float(np.median(ms[name])),
            "calls_per_frame": float(np.mean([len(frame.get(name, ())) for frame in frames])),
        }
        for name in sorted(names, key=lambda name: np.median(ms[name]), reverse=True)
    }
    stages = {
        stage: {"median_ms": median, "loops_ms": 0.0, "outside_ms": median}
        for stage, median in medians.items()
        if stage != "total"
    }
    for name, loop in loops.items():
        stage = stages.setdefault(
            stage_of(name), {"median_ms": 0.0, "loops_ms": 0.0, "outside_ms": 0.0}
        )
        stage["loops_ms"] += loop["ms_per_frame"]
        stage["outside_ms"] -= loop["ms_per_frame"]
    return {
        "threads": numba.get_num_threads(),
        "timed_frames": len(frames),
        "load_average": list(os.getloadavg()),
        "stage_medians_ms": medians,
        "loops": loops,
        "stages": stages,
        "loops_ms": sum(loop["ms_per_frame"] for loop in loops.values()),
        "minor_faults": fault_summary(list(faults)),
    }


def minor_faults() -> int:
    """The minor page faults this process has taken so far (getrusage)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_minflt


def fault_summary(faults: list[int]) -> dict[str, float] | None:
    """The median faults a frame over all frames, over the first half and over the second: a
    pipeline's heap grows over its first frames (docs/benchmarks.md), so the halves tell the
    growing frames from the steady ones. None without frames."""
    if not faults:
        return None
    half = len(faults) // 2
    return {
        "median": float(np.median(faults)),
        "first_half": float(np.median(faults[: max(half, 1)])),
        "second_half": float(np.median(faults[half:])),
    }


# The loops' packages named after their stage where the two differ.
STAGE_OF_PACKAGE = {"tsdf": "integrate", "colour": "integrate"}


def stage_of(loop: str) -> str:
    """The pipeline stage a loop named package.function runs in."""
    package = loop.split(".")[0]
    return STAGE_OF_PACKAGE.get(package, package)


def print_loop_report(report: dict[str, Any]) -> None:
    """The loop report as text: stage medians, ms and calls per frame per loop, and per stage
    the loops' ms against the rest."""
    medians = report["stage_medians_ms"]
    print(f"numba threads: {report['threads']}")
    print(f"stage medians (ms) over {report['timed_frames']} frames: {medians}")
    print("\nms per frame (median over the same frames), calls per frame (mean):")
    for name, loop in report["loops"].items():
        print(f"{loop['ms_per_frame']:8.2f} {loop['calls_per_frame']:6.1f}  {name}")
    print("\nper stage: the loops, and the stage's median less its loops")
    for stage, split in report["stages"].items():
        print(f"{stage:12s} loops {split['loops_ms']:7.2f}  outside {split['outside_ms']:7.2f}")
    total = medians["total"]
    print(f"all loops {report['loops_ms']:.2f} ms of a median frame of {total:.2f} ms")
    faults = report.get("minor_faults")
    if faults:
        print(
            f"minor page faults a frame: median {faults['median']:.0f} (first half of the frames "
            f"{faults['first_half']:.0f}, second half {faults['second_half']:.0f})"
        )
    between = report.get("between_iterations_us", {})
    if between:
        print(
            "host time between two Gauss-Newton iterations of a level (median us): "
            + ", ".join(f"{level} {us:.0f}" for level, us in between.items())
        )


if __name__ == "__main__":
    main()
