# ruff: noqa: ANN001, ANN201  (numba functions: argument types come from the call)
"""One block of ICP pairs on the CPU (icp/cpu.py's loops run it BLOCK points at a time): the
projections, the gathers of the model pixels and the rows, each in a loop of its own so that
all but the gathers vectorise; and one chunk of them summed (`icp_chunk`, what every ICP loop
runs per chunk). Also here: the ICP ops compiled once for the CPU (OPS), which icp/cpu.py's
loops call too."""

from __future__ import annotations

import numba
import numpy as np

from kintinuous_fast.odometry.sums import NV
from kintinuous_fast.odometry.sums.cpu import ALLOCATING_LOOP, BLOCK, GEOMETRY, INLINE, add_block

from .ops import build_ops

__all__ = ["OPS", "icp_chunk", "kept_pairs"]

OPS = build_ops(INLINE, GEOMETRY)
# Module-level names: numba resolves the scalar functions as globals of the loops below.
_project_nearest = OPS.project_nearest
_is_compatible = OPS.is_compatible
_transform = GEOMETRY.transform
_rotate = GEOMETRY.rotate
_point_to_plane_row = OPS.point_to_plane_row
_pair_weight = OPS.pair_weight
_weighs_pairs = OPS.weighs_pairs


@numba.njit(cache=True, error_model="numpy")
def _project_block(points, start, stop, to_model, camera, size, rows, cols):
    """_project_nearest of points[:, start:stop] into rows / cols: branch-free, so LLVM vectorises
    it (its own function: the NumPy error model leaves the guarded division without a zero test,
    and the loop with the data-dependent branches below would not vectorise). The rows are read
    as 1-d slices indexed from 0: indexed points[r, k] from `start`, numba's negative-index
    wraparound makes LLVM load them with gathers."""
    x, y, z = points[0, start:stop], points[1, start:stop], points[2, start:stop]
    for m in range(stop - start):
        rows[m], cols[m] = _project_nearest(to_model, (x[m], y[m], z[m]), camera, size)


@numba.njit(cache=True)
def _gather_model_block(rows, cols, count, mv, mn, model):
    """The model vertex and normal at each point's pixel (rows / cols; pixel (0, 0) for a point
    without one, masked out later) into model[k * BLOCK + m], k = qx, qy, qz, ux, uy, uz. A loop
    of its own: LLVM does not vectorise gathers for this CPU, and kept out of the arithmetic
    below they leave that loop free to vectorise."""
    for m in range(count):
        v, u = max(rows[m], 0), max(cols[m], 0)
        model[m], model[BLOCK + m], model[2 * BLOCK + m] = mv[v, u, 0], mv[v, u, 1], mv[v, u, 2]
        model[3 * BLOCK + m], model[4 * BLOCK + m] = mn[v, u, 0], mn[v, u, 1]
        model[5 * BLOCK + m] = mn[v, u, 2]


@INLINE
def _block_pair(columns, m, pose, rows, model, limits):
    """Pair m of a block (`columns` = its points' x, y, z, nx, ny, nz rows, sliced from its
    first point; `model` its gathered model pixels): (kept, world point, world normal, model
    vertex, model normal), the vertex and normals in float64. What both the rows and the pair
    count test, written once: inlined at numba IR level, each loop compiles as if written out."""
    x, y, z, nx, ny, nz = columns
    qx, qy, qz = float(model[m]), float(model[BLOCK + m]), float(model[2 * BLOCK + m])
    ux, uy = float(model[3 * BLOCK + m]), float(model[4 * BLOCK + m])
    uz = float(model[5 * BLOCK + m])
    world = _transform(pose, x[m], y[m], z[m])
    g = _rotate(pose, nx[m], ny[m], nz[m])
    vertex, normal = (qx, qy, qz), (ux, uy, uz)
    kept = (rows[m] >= 0) & _is_compatible(world, g, vertex, normal, limits)
    return kept, world, vertex, normal


@INLINE
def _block_columns(points, start, stop):
    """points[:, start:stop]'s six rows as 1-d slices indexed from 0 (_project_block says why)."""
    return (
        points[0, start:stop],
        points[1, start:stop],
        points[2, start:stop],
        points[3, start:stop],
        points[4, start:stop],
        points[5, start:stop],
    )


@numba.njit(cache=True, error_model="numpy")
def _icp_rows_block(points, start, stop, pose, rows, model, limits, robust, out, weighted):
    """match_pixel and point_to_plane_row (icp/ops.py) of points[:, start:stop] and their
    gathered model pixels, branch-free so that it vectorises: out[k * BLOCK + m] = (j0..j5, r, 1)
    of a kept pair, zeros for any other point (which then add nothing to the sums). Where the
    pairs have weights (`robust`: robust_terms, weighs_pairs) weighted[k * BLOCK + m] =
    w (j0..j5, r), w = pair_weight; `limits`: is_compatible's."""
    weighs = _weighs_pairs(robust)
    columns = _block_columns(points, start, stop)
    z = columns[2]
    for m in range(stop - start):
        kept, world, vertex, normal = _block_pair(columns, m, pose, rows, model, limits)
        j0, j1, j2, j3, j4, j5, r = _point_to_plane_row(world, vertex, normal)
        out[m] = j0 if kept else 0.0
        out[BLOCK + m] = j1 if kept else 0.0
        out[2 * BLOCK + m] = j2 if kept else 0.0
        out[3 * BLOCK + m] = j3 if kept else 0.0
        out[4 * BLOCK + m] = j4 if kept else 0.0
        out[5 * BLOCK + m] = j5 if kept else 0.0
        out[6 * BLOCK + m] = r if kept else 0.0
        out[7 * BLOCK + m] = 1.0 if kept else 0.0
        if weighs:
            # Selects, not products with w = 0: a rejected point's row may hold NaN (no model
            # surface at its pixel), and 0 * NaN would poison the sums.
            w = _pair_weight(r, z[m], robust)
            weighted[m] = w * j0 if kept else 0.0
            weighted[BLOCK + m] = w * j1 if kept else 0.0
            weighted[2 * BLOCK + m] = w * j2 if kept else 0.0
            weighted[3 * BLOCK + m] = w * j3 if kept else 0.0
            weighted[4 * BLOCK + m] = w * j4 if kept else 0.0
            weighted[5 * BLOCK + m] = w * j5 if kept else 0.0
            weighted[6 * BLOCK + m] = w * r if kept else 0.0


@numba.njit(cache=True, error_model="numpy")
def _kept_pairs_block(points, start, stop, pose, rows, model, limits):
    """How many of points[:, start:stop] _icp_rows_block keeps (the same _block_pair on the same
    values), without their rows: what the inlier fraction counts."""
    columns = _block_columns(points, start, stop)
    kept = 0
    for m in range(stop - start):
        kept += _block_pair(columns, m, pose, rows, model, limits)[0]
    return kept


@numba.njit(cache=True)
def kept_pairs(points, start, stop, pose, to_model, mv, mn, camera, limits, work):
    """The ICP pairs among points[:, start:stop] (_pair_rows_block's kept ones), counted in
    its projection and gather loops and a test loop that vectorises."""
    rows, cols, model = work[0], work[1], work[2]
    _project_block(points, start, stop, to_model, camera, (mv.shape[1], mv.shape[0]), rows, cols)
    _gather_model_block(rows, cols, stop - start, mv, mn, model)
    return _kept_pairs_block(points, start, stop, pose, rows, model, limits)


@numba.njit(cache=True)
def _pair_rows_block(points, start, stop, pose, to_model, mv, mn, camera, limits, robust, work):
    """The ICP rows of points[:, start:stop] (_icp_rows_block's) in three loops: projection,
    gathers, rows. All but the gathers vectorise, which one loop matching and summing pair by
    pair, with branches, would not. `camera` = (fx, fy, cx, cy), `limits` = (squared distance,
    cos angle), `robust` = robust_terms, `work` = _block_work()."""
    rows, cols, model, pair_rows, weighted_rows = work
    _project_block(points, start, stop, to_model, camera, (mv.shape[1], mv.shape[0]), rows, cols)
    _gather_model_block(rows, cols, stop - start, mv, mn, model)
    _icp_rows_block(
        points, start, stop, pose, rows, model, limits, robust, pair_rows, weighted_rows
    )


@numba.njit(cache=True)
def _block_work(dtype):
    """Work arrays of _pair_rows_block: pixel rows and columns, gathered model values (of the
    model maps' dtype), pair rows, robustly weighted pair rows."""
    return (
        np.empty(BLOCK, dtype=np.int64),
        np.empty(BLOCK, dtype=np.int64),
        np.empty(6 * BLOCK, dtype=dtype),
        np.empty(8 * BLOCK),
        np.empty(7 * BLOCK),
    )


@ALLOCATING_LOOP  # compiled as the loops are: no reference counts around its accesses
def icp_chunk(c, points, pose, to_model, mv, mn, camera, limits, robust, out):
    """Association + point-to-plane row + accumulation over chunk c (of out.shape[0]) of the
    valid current points (6, n): out[c] = the chunk's summed rows (slot NV-1: its valid
    current points). `robust` = robust_terms: the weights of the rows."""
    n = points.shape[1]
    chunks = out.shape[0]
    acc = np.zeros(NV)
    work = _block_work(mv.dtype)
    pair_matrix = work[3].reshape((8, BLOCK))
    # Least squares weighs every row by 1: its rows are their own weighted rows.
    weighs = _weighs_pairs(robust)
    weighted_matrix = work[4].reshape((7, BLOCK)) if weighs else pair_matrix
    start, stop = c * n // chunks, (c + 1) * n // chunks
    acc[NV - 1] += stop - start
    for block in range(start, stop, BLOCK):
        end = min(block + BLOCK, stop)
        _pair_rows_block(points, block, end, pose, to_model, mv, mn, camera, limits, robust, work)
        add_block(acc, weighted_matrix, pair_matrix, end - block)
    out[c] = acc
