"""What the machine itself gives a parallel loop at each thread count: the ceilings a stage's
speed-up in benchmarks/thread_sweep.py is read against.

    python benchmarks/machine_scaling.py [--threads 1,2,4,8,16] [--repeats 5] [--json OUT]

Three loops on numba's threads (prange, the threading layer the pipeline's loops use), each cut
into many equal parts so that every count shares the same work:
- compute: a dependent chain of multiply-adds and square roots per part, no memory; its speed-up
  is how many cores the threads really get (below the count where cores are hyperthreads or
  shared with other jobs);
- bandwidth, frame-sized: a triad a = b + s c over three arrays of a 640x480 vertex map's size
  (3.7 MB each): data an odometry or preprocessing loop streams, which a large last-level cache
  may hold;
- bandwidth, volume-sized: the same triad over three arrays of a 256^3 float32 TSDF's size
  (67 MB each), which come from memory.
A triad's GB/s counts the bytes it reads and writes (3 arrays a call; not the cache's
write-allocate reads). Each number is the best of `--repeats` calls after a warm-up call: a
ceiling, what the machine can give, not what it usually gives. A stage whose speed-up follows
the bandwidth rows rather than the compute row is limited by memory, where fewer bytes a frame,
not fewer calls, would help it.
"""

from __future__ import annotations

import argparse
import json
import math
import time
from pathlib import Path
from typing import Any

import numba
import numpy as np

# Parts each loop is cut into: many more than threads, so that every count shares them evenly.
PARTS = 512
# The triads' array sizes: a 640x480x3 float32 map, a 256^3 float32 volume (float64 elements).
FRAME_ELEMENTS = 640 * 480 * 3 // 2
VOLUME_ELEMENTS = 256**3 // 2
# Steps of the compute loop's chain per part: about 25 ms on one core of the 2-core VM.
COMPUTE_STEPS = 5_000


@numba.njit(parallel=True, cache=True)
def compute_chain(parts: int, steps: int) -> np.ndarray:
    """Each part's dependent chain x <- sqrt(x * 1.0000001 + 1e-9): no memory, no vectors."""
    out = np.empty(parts)
    for part in numba.prange(parts):
        x = 1.0 + part
        for _ in range(steps):
            x = math.sqrt(x * 1.0000001 + 1e-9)
        out[part] = x
    return out


@numba.njit(parallel=True, cache=True)
def triad(a: np.ndarray, b: np.ndarray, c: np.ndarray, scale: float, parts: int) -> None:
    """a = b + scale c, part by part (each part a contiguous range)."""
    n = a.size
    for part in numba.prange(parts):
        for i in range(n * part // parts, n * (part + 1) // parts):
            a[i] = b[i] + scale * c[i]


def best_seconds(call: Any, repeats: int) -> float:
    """The least wall time of `repeats` calls after a warm-up call (compilation, first touch)."""
    call()
    times = []
    for _ in range(repeats):
        started = time.perf_counter()
        call()
        times.append(time.perf_counter() - started)
    return min(times)


def triad_gb_per_s(elements: int, seconds: float) -> float:
    """GB/s of one triad over float64 arrays of `elements`: two read and one written."""
    return 3 * 8 * elements / seconds / 1e9


def measure(counts: list[int], repeats: int) -> dict[str, Any]:
    """Per thread count: the compute loop's seconds, both triads' GB/s, and each one's speed-up
    against the first count."""
    arrays = {
        size: tuple(np.full(elements, 1.0 + k) for k in range(3))
        for size, elements in (("frame", FRAME_ELEMENTS), ("volume", VOLUME_ELEMENTS))
    }
    rows: dict[int, dict[str, float]] = {}
    for threads in counts:
        numba.set_num_threads(threads)
        row = {"compute_s": best_seconds(lambda: compute_chain(PARTS, COMPUTE_STEPS), repeats)}
        for size, (a, b, c) in arrays.items():
            seconds = best_seconds(lambda a=a, b=b, c=c: triad(a, b, c, 3.0, PARTS), repeats)
            row[f"{size}_gb_s"] = triad_gb_per_s(a.size, seconds)
        rows[threads] = row
    return {"threads": counts, "rows": rows, "speedups": speedups(rows)}


def speedups(rows: dict[int, dict[str, float]]) -> dict[str, dict[int, float]]:
    """Per loop (compute, frame, volume), each count's speed-up against the first count."""
    base = rows[min(rows)]
    return {
        "compute": {n: base["compute_s"] / row["compute_s"] for n, row in rows.items()},
        "frame": {n: row["frame_gb_s"] / base["frame_gb_s"] for n, row in rows.items()},
        "volume": {n: row["volume_gb_s"] / base["volume_gb_s"] for n, row in rows.items()},
    }


def table(result: dict[str, Any]) -> list[str]:
    """The measurement as text: GB/s and speed-ups per thread count."""
    counts, rows, ups = result["threads"], result["rows"], result["speedups"]
    head = "".join(f"{n:>9d}" for n in counts)
    lines = [f"machine ceilings per thread count (best of the calls), speed-up against {counts[0]}"]
    lines.append(f"{'':28s}{head}")
    for label, values in (
        ("compute, ms", [1e3 * rows[n]["compute_s"] for n in counts]),
        ("compute, speed-up", [ups["compute"][n] for n in counts]),
        ("frame triad, GB/s", [rows[n]["frame_gb_s"] for n in counts]),
        ("frame triad, speed-up", [ups["frame"][n] for n in counts]),
        ("volume triad, GB/s", [rows[n]["volume_gb_s"] for n in counts]),
        ("volume triad, speed-up", [ups["volume"][n] for n in counts]),
    ):
        lines.append(f"{label:28s}" + "".join(f"{value:9.2f}" for value in values))
    return lines


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--threads", default="1,2,4,8,16", help="comma-separated counts")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--json", type=Path, help="write the measurement here")
    args = parser.parse_args()
    asked = sorted({int(part) for part in args.threads.split(",") if part.strip()})
    counts = [n for n in asked if 1 <= n <= numba.config.NUMBA_NUM_THREADS]
    if len(counts) < len(asked):
        print(f"numba has {numba.config.NUMBA_NUM_THREADS} threads: skipped the larger counts")
    if not counts:
        parser.error("no thread count fits numba's threads")
    result = measure(counts, args.repeats)
    print("\n".join(table(result)))
    if args.json:
        args.json.write_text(json.dumps(result, indent=1) + "\n")


if __name__ == "__main__":
    main()
