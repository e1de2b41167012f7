"""The normal equations as both targets sum them: one vector of NV float64 values per thread,
chunk or block, added up on the host and unpacked into a LinearSystem.

The vector holds the 21 upper-triangle entries of A = J^T W J (row-major, i <= j), the 6 entries
of b = J^T W r, the cost r^T W r, the count of rows and one spare slot (the ICP kernels count the
valid current points there, which the inlier fraction needs). `ops.py` adds one row to it (both
targets), `cpu.py` sums rows in fixed chunks and blocks, `cuda.py` reduces a block's vectors by
a tree in shared memory; the partials come back here (sum_partials).
"""

from __future__ import annotations

import numpy as np

from kintinuous_ref.odometry.solve import LinearSystem

# Slots of the accumulated vector.
NV = 30
SLOT_B = 21
SLOT_COST = 27
SLOT_COUNT = 28
SLOT_EXTRA = 29

# Upper-triangle (i, j) pairs of A in the order of the accumulated vector (ops.add_row).
_UPPER = [(i, j) for i in range(6) for j in range(i, 6)]
_UPPER_ROWS, _UPPER_COLS = (np.array(index) for index in zip(*_UPPER, strict=True))


def unpack(total: np.ndarray) -> tuple[LinearSystem, int]:
    """(LinearSystem, the spare slot as an int) from the NV summed float64 values."""
    A = np.empty((6, 6))
    A[_UPPER_ROWS, _UPPER_COLS] = A[_UPPER_COLS, _UPPER_ROWS] = total[:SLOT_B]
    count = int(round(total[SLOT_COUNT]))
    system = LinearSystem(A, total[SLOT_B : SLOT_B + 6].copy(), count, float(total[SLOT_COST]))
    return system, int(round(total[SLOT_EXTRA]))


def sum_partials(partials: np.ndarray) -> tuple[LinearSystem, int]:
    """Sum per-chunk / per-block partials (rows, NV) in float64 on the host and unpack them."""
    return unpack(np.asarray(partials, dtype=np.float64).reshape(-1, NV).sum(axis=0))


def chunks_for(count: int, chunks: int) -> int:
    """How many fixed chunks a loop over `count` items is split into (>= 1)."""
    return max(1, min(chunks, count))
