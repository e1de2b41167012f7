"""The normal equations summed on the CPU, and what both estimators' loops share there.

Sums never race and never depend on the thread count: each loop is split into a FIXED number of
chunks (CHUNKS), every chunk sums its rows into its own float64 row of partials (`partials`),
and the host adds the partials (sums.sum_partials). Results are therefore the same on any number
of threads, run after run. Inside a chunk the rows go through blocks of BLOCK (`add_block`).

The per-element ops both estimators call (odometry/ops.py's geometry, sums/ops.py's add_row) are
compiled here once for the CPU, inlined into the loops at numba IR level (INLINE): compiled
separately, LLVM does not inline the larger ops (icp_match and warp_point take 4-8 arrays, i.e.
dozens of scalar arguments), and a call per pixel costs several times the arithmetic it wraps.
"""

from __future__ import annotations

from typing import Any

import numba
import numpy as np

from kintinuous_fast.odometry import ops as geometry_ops
from kintinuous_fast.targets import to_host
from kintinuous_fast.targets.cpu import claimed_items, parallel_part, run_parallel

from . import NV, SLOT_B, SLOT_COST, SLOT_COUNT, chunks_for
from .ops import build_ops

__all__ = [
    "ALLOCATING_LOOP",
    "BLOCK",
    "CHUNKS",
    "GEOMETRY",
    "INLINE",
    "LOOP",
    "add_block",
    "add_column",
    "add_row",
    "partials",
    "row_starts",
    "run",
    "stage",
]

# Chunks per reduction loop: enough to keep every core busy, few enough that the partials cost
# nothing to add up. Fixed, so that the order of summation never depends on the thread count.
CHUNKS = 64
# Points per block of the ICP and RGB-D loops: a block's projections are computed first, in a
# loop that vectorises (divisions and roundings 8 at a time), into a buffer that stays in L1.
BLOCK = 128

# The decorator of every per-element op on the CPU (module docstring).
INLINE = numba.njit(cache=True, inline="always")
GEOMETRY = geometry_ops.build_ops(INLINE)
# Module-level names: numba resolves the scalar functions as globals of the loops that call
# them.
_ops = build_ops(INLINE)
add_row = _ops.add_row
add_column = _ops.add_column

# The decorators of the odometry's CPU loops (run by `run`): LOOP for those that allocate
# nothing, ALLOCATING_LOOP for those with work arrays of their own.
LOOP = parallel_part()
ALLOCATING_LOOP = parallel_part(_nrt=True)


@numba.njit(cache=True, fastmath={"reassoc"})
def add_block(acc, weighted, rows, count):  # noqa: ANN001, ANN201
    """add_row of a block's first `count` rows, as sums over the block entry by entry so that
    each vectorises: rows = (j0..j5, r, 1 or 0 for a row to count), weighted = (w j0..w j5, w r)
    (the ICP passes its rows as both). Reassociated within the block: the order of the
    additions still depends on BLOCK only, never on the thread count."""
    slot = 0
    for i in range(6):
        a = weighted[i]
        for j in range(i, 7):
            b = rows[j]
            total = 0.0
            for m in range(count):
                total += a[m] * b[m]
            acc[SLOT_B + i if j == 6 else slot] += total
            slot += j < 6
    for target, a, b in ((SLOT_COST, weighted[6], rows[6]), (SLOT_COUNT, rows[7], rows[7])):
        total = 0.0
        for m in range(count):
            total += a[m] * b[m]
        acc[target] += total


@LOOP
def _copy_map_rows(claims, parts, source, target):  # noqa: ANN001, ANN202
    """target[v] = source[v] for the rows v this thread claims of (h, w, 3) maps: NumPy copies
    a strided map 3 values at a time, this unrolled loop whole pixels."""
    for v in claimed_items(claims, source.shape[0], parts):
        for u in range(source.shape[1]):
            target[v, u, 0] = source[v, u, 0]
            target[v, u, 1] = source[v, u, 1]
            target[v, u, 2] = source[v, u, 2]


def stage(array: Any) -> Any:
    """Arrays as the loops take them: C-contiguous NumPy (device arrays are downloaded). One
    layout means one compiled specialisation per loop (the model pyramid's strided levels are
    copied once per frame, on every thread: the copy reads the raycast's maps, which are
    seldom still in the cache by then, so it waits on memory, which two cores fetch faster
    than one)."""
    if array is None:
        return None
    array = to_host(array)
    if array.ndim == 3 and array.shape[2] == 3 and not array.flags.c_contiguous:
        copy = np.empty(array.shape, dtype=array.dtype)
        run_parallel(_copy_map_rows, array, copy)
        return copy
    return np.ascontiguousarray(array)


def run(loop: Any, count: int, *args: Any) -> None:
    """run_parallel a loop over `count` items: on as many threads as its measured work per item
    repays (kintinuous_fast.targets.cpu.threads_for), the calling thread alone for the small
    loops of the coarse levels."""
    run_parallel(loop, *args, items=count)


def row_starts(counts: np.ndarray) -> tuple[np.ndarray, int]:
    """(each row's first column, the total) of a compaction whose rows keep counts[v] items:
    what a loop writing row v from column starts[v] needs to keep the row-major order."""
    starts = np.zeros_like(counts)
    np.cumsum(counts[:-1], out=starts[1:])
    return starts, int(counts.sum())


def partials(count: int) -> np.ndarray:
    """Zeroed per-chunk partial sums for a loop over `count` rows."""
    return np.zeros((chunks_for(count, CHUNKS), NV))
