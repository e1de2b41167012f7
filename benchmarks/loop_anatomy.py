"""Why a cpu loop on N threads takes longer than its one-thread time divided by N: each parallel
loop of a pipeline run replayed alone, on one thread and on N, with every thread's entry and
exit timed.

    python benchmarks/loop_anatomy.py DATASET [--frames 6] [--calls 30] [--top 25] [--json F]

The pipeline runs `--frames` frames on the cpu backend (the default configuration, `--set`
overrides), and the last call of every loop that `run_parallel` launches, and each level of
the joint ICP + RGB-D loop, is kept. Each is then called `--calls` times on one thread and on
numba's N threads, alternated, through the loop's own launcher, wrapped so that each thread
reads the clock as it enters the loop and as it leaves; in the parts its caller gave, or where
it gave none in those run_parallel gives a loop on that many threads. Per loop, medians over
the calls, in microseconds, the time on N threads less the ideal (one thread's time / N),
split into:
- wake-up: from the calling thread's entry to the last thread's;
- join: from the last thread's exit until the call has returned to Python;
- imbalance: from the first thread's exit to the last's, while the first waits;
- inflation: the threads' busy time summed, less the one thread's, over N: how much more the
  same work costs each thread while the others run (shared caches, memory bandwidth, a cache
  line two threads write), and, in a loop of two passes, the time a thread waits between them.
What is left over is the dispatch from Python and the clock itself (a few microseconds). A
loop that wants fewer threads shows a large wake-up or join against its time; one held back
by memory or false sharing shows a large inflation.
"""

from __future__ import annotations

import argparse
import ctypes
import json
import statistics
import time
import warnings
from functools import cache
from pathlib import Path
from types import FunctionType
from typing import Any

import numba
import numpy as np

import kintinuous_fast.odometry.icp.cpu_joint as joint
from kintinuous_fast.targets import cpu, cpu_probe
from kintinuous_ref.config import Config, with_overrides
from kintinuous_ref.program.benchmark import benchmark, machine_line

_clock_gettime = ctypes.CDLL(None).clock_gettime
_clock_gettime.argtypes = [ctypes.c_int, ctypes.c_void_p]
_clock_gettime.restype = ctypes.c_int
MONOTONIC = time.CLOCK_MONOTONIC


@numba.njit(nogil=True)
def now_ns(buffer: np.ndarray) -> int:
    """CLOCK_MONOTONIC in nanoseconds, the clock of Python's time.monotonic_ns; `buffer`: this
    thread's own two int64 (a timespec)."""
    _clock_gettime(MONOTONIC, buffer.ctypes.data)
    return buffer[0] * 1_000_000_000 + buffer[1]


def _traced(claims, parts, args, log, count):  # noqa: ANN001, ANN202 (numba: types from the call)
    """LOOP(claims, parts, *args), this thread's entry and exit time into the next row of log."""
    buffer = np.empty(2, dtype=np.int64)
    entered = now_ns(buffer)
    LOOP(claims, parts, *args)  # noqa: F821 (each traced loop's own global)
    left = now_ns(buffer)
    row = cpu.atomic_fetch_add(count, 0)
    log[row, 0], log[row, 1] = entered, left


@cache
def traced(loop: Any) -> Any:
    """`loop` wrapped by _traced, with the loop as its global (as targets.cpu.launcher's): a
    function of its own per loop, dispatched from Python as the loop's launcher is."""
    names = {"LOOP": loop, "now_ns": now_ns, "cpu": cpu, "np": np}
    function = FunctionType(_traced.__code__, names, f"traced_{loop.py_func.__name__}")
    return cpu.parallel_part(_nrt=True, cache=False)(function)


class Capture:
    """The last call of each loop that run_parallel launches, kept while it is installed, and
    each joint level's (the joint loop runs from compiled code, not through run_parallel)."""

    def __init__(self) -> None:
        # name: (loop, arguments, parts as the caller gave them, counters and their values)
        self.calls: dict[str, tuple[Any, tuple, int | None, list]] = {}
        self._refine = joint.JointLevel.refine
        self._replaced = cpu_probe.run_parallel_replaced(self._keeping)

    def _keeping(self, run_parallel: Any) -> Any:
        """run_parallel, each loop's call kept in `calls` first."""

        def kept(loop: Any, *args: Any, parts: int | None = None, **kw: Any) -> None:
            self.calls[cpu_probe.loop_name(loop)] = (loop, args, parts, counters(args))
            run_parallel(loop, *args, parts=parts, **kw)

        return kept

    def __enter__(self) -> Capture:
        capture = self

        def refine(level: joint.JointLevel, pose: np.ndarray, *rest: Any) -> Any:
            if level.kind == joint.JOINT:
                args = level.arguments(pose)
                name = f"odometry._joint_loop L{level.level}"
                zeroed = [(level.corresponded, np.zeros_like(level.corresponded))]
                capture.calls[name] = (joint._joint_loop, args, level.parts, zeroed)
            return capture._refine(level, pose, *rest)

        joint.JointLevel.refine = refine
        self._replaced.__enter__()
        return self

    def __exit__(self, *exc: object) -> None:
        self._replaced.__exit__(*exc)
        joint.JointLevel.refine = self._refine


def counters(args: tuple) -> list[tuple[np.ndarray, np.ndarray]]:
    """The small int64 arrays among a loop's arguments, with their values before the call:
    counters that the loop's threads advance (threads that painted, chunks done), which a
    replay sets back, or it would read past what they count."""
    small = [a for a in args if isinstance(a, np.ndarray) and a.dtype == np.int64 and a.size <= 8]
    return [(array, array.copy()) for array in small]


def timed_call(
    loop: Any, args: tuple, parts: int | None, team: int, resets: list
) -> dict[str, float]:
    """One call of the traced loop on `team` threads, in `parts` parts (None: as run_parallel
    cuts a loop that runs on `team` threads), each of `resets`' counters set back first: its
    call, wake-up, join, imbalance and busy time in microseconds."""
    parts = cpu.PARTS_PER_THREAD * team if parts is None else parts
    for counter, before in resets:
        counter[:] = before
    log, count = np.zeros((team, 2), dtype=np.int64), np.zeros(1, dtype=np.int64)
    claims = np.zeros(3, dtype=np.int64)
    launch = cpu.launcher(traced(loop))
    with warnings.catch_warnings():
        # the clock's ctypes pointer keeps traced loops and their launchers out of numba's cache
        warnings.filterwarnings("ignore", message="Cannot cache compiled function")
        started = time.monotonic_ns()
        launch(team, claims, parts, args, log, count)
        returned = time.monotonic_ns()
    entered, left = log[: count[0], 0], log[: count[0], 1]
    return {
        "call": (returned - started) / 1e3,
        "wake": (entered.max() - entered.min()) / 1e3,
        "join": (returned - left.max()) / 1e3,
        "imbalance": (left.max() - left.min()) / 1e3,
        "busy": float((left - entered).sum()) / 1e3,
    }


def anatomy(
    loop: Any, args: tuple, parts: int | None, resets: list, team: int, calls: int
) -> dict[str, float]:
    """Medians of `calls` traced calls on one thread and on `team`, alternated, after one of
    each (compilation), and the time on `team` less the ideal split as the docstring says."""
    timed_call(loop, args, parts, 1, resets)
    timed_call(loop, args, parts, team, resets)
    one, many = [], []
    for _ in range(calls):
        one.append(timed_call(loop, args, parts, 1, resets))
        many.append(timed_call(loop, args, parts, team, resets))

    def median(samples: list[dict[str, float]], key: str) -> float:
        return statistics.median(sample[key] for sample in samples)

    alone, shared = median(one, "call"), median(many, "call")
    busy_alone = median(one, "busy")
    return {
        "one_us": alone,
        "team_us": shared,
        "lost_us": shared - alone / team,
        "wake_us": median(many, "wake"),
        "join_us": median(many, "join"),
        "imbalance_us": median(many, "imbalance"),
        "inflation_us": (median(many, "busy") - busy_alone) / team,
    }


COLUMNS = ("one_us", "team_us", "lost_us", "wake_us", "join_us", "imbalance_us", "inflation_us")


def table(rows: dict[str, dict[str, float]], team: int, top: int) -> list[str]:
    """The loops with the most time lost first, a line each."""
    heads = ("1 thread", f"{team} thr.", "lost", "wake-up", "join", "imbal.", "inflat.")
    lines = [f"microseconds a call, medians; lost = on {team} threads less 1 thread's / {team}"]
    lines.append("".join(f"{head:>10s}" for head in heads) + "  loop")
    ordered = sorted(rows.items(), key=lambda item: -item[1]["lost_us"])
    for name, row in ordered[:top]:
        lines.append("".join(f"{row[key]:10.1f}" for key in COLUMNS) + f"  {name}")
    return lines


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("dataset", help="TUM folder or synthetic scenario name")
    parser.add_argument("--frames", type=int, default=6)
    parser.add_argument("--calls", type=int, default=30)
    parser.add_argument("--top", type=int, default=25, help="loops listed")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    parser.add_argument("--json", type=Path, help="write every loop's numbers here")
    args = parser.parse_args()
    overrides = {key: json.loads(value) for key, _, value in (s.partition("=") for s in args.set)}
    config = with_overrides(Config(), overrides)
    team = cpu.threads()
    if team < 2:
        parser.error("numba has one thread here: nothing to compare (NUMBA_NUM_THREADS)")
    with Capture() as capture:
        benchmark(args.dataset, frames=args.frames, backend="cpu", config=config)
    rows = {
        name: anatomy(loop, loop_args, parts, resets, team, args.calls)
        for name, (loop, loop_args, parts, resets) in sorted(capture.calls.items())
    }
    print(machine_line())
    print("\n".join(table(rows, team, args.top)))
    if args.json:
        args.json.write_text(json.dumps({"threads": team, "loops": rows}, indent=1) + "\n")


if __name__ == "__main__":
    main()
