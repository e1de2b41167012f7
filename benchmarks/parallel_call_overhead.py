"""What a parallel call costs on the CPU: the project's run_parallel on each of its paths (numba's
threads through a launcher per loop, where numba's threading layer spins; the helper threads
that call the loop from Python) against a numba gufunc on numba's threading layer
(`guvectorize`, target "parallel", the outer dimension being the parts), on the same
synthetic loop.

    python benchmarks/parallel_call_overhead.py [--calls 400] [--gaps 0,20,100] [--at-most N]

The loop does `reps` multiply-adds on each of 64 items, cut into 8 parts. Between two calls the
calling thread runs Python for `gap` microseconds, as the odometry does between its loops (the
GIL held). Prints numba's threading layer, then the median time of a call in microseconds: on
one thread, through run_parallel on each path and through the gufunc, and each one's speed-up
over one thread (docs/benchmarks.md); then how long a call takes that every thread of a team
of 2, 3, ... must join (a rendezvous of one part per thread), on each path: the cost of
starting a whole team.
"""

from __future__ import annotations

import argparse
import statistics
import time
from collections.abc import Callable

import numba
import numpy as np
from numba import guvectorize

from kintinuous_fast.targets import cpu
from kintinuous_fast.targets.cpu import (
    LOOP_COSTS,
    atomic_fetch_add,
    claimed_items,
    parallel_part,
    run_parallel,
    spin_below,
)

ITEMS, PARTS = 64, 8


@numba.njit(cache=True)
def _multiply_adds(x: float, reps: int) -> float:
    for _ in range(reps):
        x = x * 1.0000001 + 1e-9
    return x


@parallel_part()
def _helper_loop(claims, parts, values, reps):  # noqa: ANN001, ANN202
    for item in claimed_items(claims, values.shape[0], parts):
        values[item] = _multiply_adds(values[item], reps)


@parallel_part()
def _rendezvous(claims, parts, arrived, spins):  # noqa: ANN001, ANN202
    """One part per thread, each waiting until every part has begun (at most `spins` loads):
    the call lasts until the last thread of the team has joined."""
    for _ in claimed_items(claims, parts, parts):
        atomic_fetch_add(arrived, 0)
        spin_below(arrived, 0, parts, spins)


def team_join(threads: int, calls: int) -> float:
    """Median microseconds of a call that every one of `threads` threads must join."""
    arrived = np.zeros(1, dtype=np.int64)

    def call() -> None:
        arrived[0] = 0
        LOOP_COSTS.per_item.pop(_rendezvous, None)  # unknown work: every thread joins
        run_parallel(_rendezvous, arrived, 2_000_000, parts=threads)

    return median_call(call, 100, calls)


@guvectorize(
    ["void(int64, int64, float64[:], int64, float64[:])"],
    "(),(),(n),()->()",
    target="parallel",
    nopython=True,
    cache=True,
)
def _gufunc_part(part, parts, values, reps, done):  # noqa: ANN001, ANN202
    n = values.shape[0]
    for item in range(n * part // parts, n * (part + 1) // parts):
        values[item] = _multiply_adds(values[item], reps)
    done[0] = 1.0


def _busy(microseconds: float) -> None:
    end = time.perf_counter() + microseconds * 1e-6
    while time.perf_counter() < end:
        pass


def median_call(call: Callable[[], None], gap: float, calls: int) -> float:
    """Median microseconds of `call`, with `gap` microseconds of Python before each."""
    call()
    times = []
    for _ in range(calls):
        _busy(gap)
        started = time.perf_counter()
        call()
        times.append(time.perf_counter() - started)
    return 1e6 * statistics.median(times)


PATHS = {"numba's threads": True, "helper team": False}


def on_path(native: bool, call: Callable[[], float]) -> float | None:
    """call() with run_parallel on numba's threads (native) or on the helper team; None where
    numba's threading layer does not spin (run_parallel then always takes the team)."""
    if native and not cpu.native_threads():
        return None
    spins = cpu.native_threads
    cpu.native_threads = lambda: native
    try:
        return call()
    finally:
        cpu.native_threads = spins


def speed(one: float, time_us: float | None) -> str:
    return f"{'-':>10s} {'':6s}" if time_us is None else f"{time_us:10.1f} ({one / time_us:4.2f})"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--calls", type=int, default=400)
    parser.add_argument("--gaps", default="0,20,100", help="microseconds of Python between calls")
    parser.add_argument(
        "--at-most",
        type=int,
        help="numba.set_num_threads: loops on at most this many threads while the helper team "
        "keeps NUMBA_NUM_THREADS - 1 helpers (a large team, loops that want few of them)",
    )
    args = parser.parse_args()
    if args.at_most:
        numba.set_num_threads(args.at_most)
    spins = cpu.native_threads()  # numba's threading layer started
    layer = numba.threading_layer()
    if not spins:
        layer += " (it does not spin: run_parallel takes the helper team)"
    print(f"NUMBA_NUM_THREADS {numba.config.NUMBA_NUM_THREADS}, loops on at most "
          f"{numba.get_num_threads()}, threading layer {layer}")  # fmt: skip
    values = np.ones(ITEMS)
    parts = np.arange(PARTS, dtype=np.int64)
    done = np.empty(PARTS)
    print("gap us  work reps |  one thread  numba's threads (x)   helper team (x)   gufunc (x)")
    for gap in (int(text) for text in args.gaps.split(",")):
        for reps in (200, 500, 2000, 20000):

            def shared(reps: int = reps, gap: int = gap) -> float:
                return median_call(
                    lambda: run_parallel(_helper_loop, values, reps), gap, args.calls
                )

            one = median_call(lambda r=reps: run_parallel(_helper_loop, values, r, parts=1),
                              gap, args.calls)  # fmt: skip
            gufunc = median_call(lambda r=reps: _gufunc_part(parts, PARTS, values, r, done),
                                 gap, args.calls)  # fmt: skip
            times = [on_path(native, shared) for native in PATHS.values()] + [gufunc]
            print(f"{gap:6d} {reps:10d} | {one:10.1f} " + "  ".join(speed(one, t) for t in times))
    # How long a whole team takes to join one call: a helper takes the GIL in turn to join (its
    # Python between the watch and the loop), so this grows with the team if that is what a
    # large team waits for; numba's threads join from native code.
    for name, native in PATHS.items():
        joins = {
            n: on_path(native, lambda n=n: team_join(n, args.calls))
            for n in range(2, numba.get_num_threads() + 1)
        }
        print(f"team join on {name}, 100 us of Python before each call: " + ", ".join(
            "-" if us is None else f"{n} threads {us:.0f} us" for n, us in joins.items()
        ))  # fmt: skip


if __name__ == "__main__":
    main()
