# ruff: noqa: ANN001, ANN201  (numba loops: argument types come from the call)
"""kintinuous_ref.odometry on the CPU: loops on all threads around kintinuous_fast.odometry.ops.

Same public names, signatures and results as the reference modules icp.py, rgbd.py, solve.py and
combined.py (tests/test_fast_odometry.py states the tolerances). The normal equations are summed
without racing: each loop is split into a FIXED number of chunks (CHUNKS, independent of the
thread count), every chunk sums its rows into its own float64 row of partials, and the host adds
the partials. Results are therefore the same on any number of threads, run after run. Lists
(interest points, correspondences) come out in the reference's order.
"""

from __future__ import annotations

import sys

import numba
import numpy as np

from kintinuous_fast.odometry import host
from kintinuous_fast.targets import pinhole
from kintinuous_fast.targets.cpu import (
    claim_slot,
    claimed_items,
    parallel_part,
    run_parallel_above,
    threads,
)
from kintinuous_ref.camera import Intrinsics
from kintinuous_ref.config import Config, IcpConfig
from kintinuous_ref.odometry import METHODS, Tracker, TrackingResult
from kintinuous_ref.odometry.combined import icp_scale
from kintinuous_ref.odometry.icp import robust_threshold
from kintinuous_ref.odometry.rgbd import Correspondences, InterestPoints
from kintinuous_ref.odometry.solve import LinearSystem
from kintinuous_ref.preprocess import model_pyramid

from .ops import NV, SLOT_B, SLOT_COST, SLOT_COUNT, build_ops
from .solve import CombinedProblem, apply_increment, joint_system, refine, solve

__all__ = [
    "METHODS",
    "CombinedProblem",
    "DenseTracker",
    "TrackingResult",
    "Correspondences",
    "IcpProblem",
    "InterestPoints",
    "LinearSystem",
    "RgbdProblem",
    "accumulate",
    "apply_increment",
    "associate",
    "correspond",
    "icp_scale",
    "icp_system",
    "interest_points",
    "joint_system",
    "make_tracker",
    "model_pyramid",
    "photometric_rows",
    "point_to_plane_rows",
    "prepare_level",
    "refine",
    "rgbd_system",
    "solve",
]

# Chunks per reduction loop: enough to keep every core busy, few enough that the partials cost
# nothing to add up. Fixed, so that the order of summation never depends on the thread count.
CHUNKS = 64
# Loops over fewer items than this run on the calling thread only (see _run). At 10 000 the
# RGB-D systems (~35 000 interest points at level 0) and the coarse levels run on both cores:
# a default icp+rgbd track took 67 instead of 84 ms (median, 2 threads, interleaved A/B).
PARALLEL_MIN = 10_000
# Points per block of the ICP loop: the block's projections are computed first, in a loop that
# vectorises (divisions and roundings 8 at a time), into a buffer that stays in L1.
BLOCK = 128

# The per-pair ops are inlined into the loops at numba IR level: compiled separately, LLVM does not
# inline the larger ones (icp_match, warp_point take 4-8 arrays, i.e. dozens of scalar arguments),
# and the call per pixel cost 2.6x in the RGB-D loop and 1.2x in the ICP loop (bit-identical).
_ops = build_ops(numba.njit(cache=True, inline="always"))
# Module-level names: numba resolves the scalar functions as globals of the loops below.
icp_match = _ops.icp_match
project_nearest = _ops.project_nearest
is_compatible = _ops.is_compatible
transform = _ops.transform
rotate = _ops.rotate
map_point = _ops.map_point
point_to_plane_row = _ops.point_to_plane_row
pair_weight = _ops.pair_weight
weighs_pairs = _ops.weighs_pairs
NO_WEIGHTS = host.NO_WEIGHTS
is_interest = _ops.is_interest
has_depth = _ops.has_depth
backproject = _ops.backproject
warp_point = _ops.warp_point
warp_project = _ops.warp_project
warp_sample = _ops.warp_sample
photometric_row = _ops.photometric_row
robust_weight = _ops.robust_weight
add_row = _ops.add_row

_loop = parallel_part()
_allocating_loop = parallel_part(_nrt=True)  # for loops with work arrays of their own


# ----------------------------------------------------------------------------------------------
# Loops


@_loop
def _valid_counts(claims, parts, vertices, normals, counts):
    """counts[v] = the valid current points (finite vertex and normal) of row v."""
    for v in claimed_items(claims, vertices.shape[0], parts):
        count = 0
        for u in range(vertices.shape[1]):
            count += map_point(vertices, normals, v, u)[0]
        counts[v] = count


@_loop
def _compact_loop(claims, parts, vertices, normals, starts, points):
    """The valid current points as columns (px, py, pz, nx, ny, nz) in row-major order, row v's
    from column starts[v]."""
    for v in claimed_items(claims, vertices.shape[0], parts):
        k = starts[v]
        for u in range(vertices.shape[1]):
            ok, px, py, pz, nx, ny, nz = map_point(vertices, normals, v, u)
            if ok:
                points[0, k], points[1, k], points[2, k] = px, py, pz
                points[3, k], points[4, k], points[5, k] = nx, ny, nz
                k += 1


@numba.njit(cache=True, error_model="numpy")
def _project_block(points, start, stop, to_model, camera, size, rows, cols):
    """project_nearest of points[:, start:stop] into rows / cols: branch-free, so LLVM vectorises
    it (its own function: the NumPy error model leaves the guarded division without a zero test,
    and the loop with the data-dependent branches below would not vectorise). The rows are read
    as 1-d slices indexed from 0: indexed points[r, k] from `start`, numba's negative-index
    wraparound made LLVM load them with gathers (ICP level 0: 6.0 -> 4.6 ms single-thread)."""
    x, y, z = points[0, start:stop], points[1, start:stop], points[2, start:stop]
    for m in range(stop - start):
        rows[m], cols[m] = project_nearest(to_model, (x[m], y[m], z[m]), camera, size)


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


@numba.njit(cache=True, error_model="numpy")
def _icp_rows_block(points, start, stop, pose, rows, model, limits, robust, out, weighted):
    """match_pixel and point_to_plane_row of points[:, start:stop] and their gathered model
    pixels, branch-free so that it vectorises: out[k * BLOCK + m] = (j0..j5, r, 1) of a kept pair,
    zeros for any other point (which then add nothing to the sums). Where the pairs have
    weights (`robust`: host.robust_terms, weighs_pairs) weighted[k * BLOCK + m] =
    w (j0..j5, r), w = pair_weight; `limits`: is_compatible's."""
    weighs = weighs_pairs(robust)
    x, y, z = points[0, start:stop], points[1, start:stop], points[2, start:stop]
    nx, ny, nz = points[3, start:stop], points[4, start:stop], points[5, start:stop]
    for m in range(stop - start):
        qx, qy, qz = float(model[m]), float(model[BLOCK + m]), float(model[2 * BLOCK + m])
        ux, uy = float(model[3 * BLOCK + m]), float(model[4 * BLOCK + m])
        uz = float(model[5 * BLOCK + m])
        world = transform(pose, x[m], y[m], z[m])
        g = rotate(pose, nx[m], ny[m], nz[m])
        vertex, normal = (qx, qy, qz), (ux, uy, uz)
        kept = (rows[m] >= 0) & is_compatible(world, g, vertex, normal, limits)
        j0, j1, j2, j3, j4, j5, r = point_to_plane_row(world, vertex, normal)
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
            w = pair_weight(r, z[m], robust)
            weighted[m] = w * j0 if kept else 0.0
            weighted[BLOCK + m] = w * j1 if kept else 0.0
            weighted[2 * BLOCK + m] = w * j2 if kept else 0.0
            weighted[3 * BLOCK + m] = w * j3 if kept else 0.0
            weighted[4 * BLOCK + m] = w * j4 if kept else 0.0
            weighted[5 * BLOCK + m] = w * j5 if kept else 0.0
            weighted[6 * BLOCK + m] = w * r if kept else 0.0


@numba.njit(cache=True, fastmath={"reassoc"})
def _add_block(acc, weighted, rows, count):
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


@numba.njit(cache=True)
def _pair_rows_block(points, start, stop, pose, to_model, mv, mn, camera, limits, robust, work):
    """The ICP rows of points[:, start:stop] (_icp_rows_block's) in three loops: projection,
    gathers, rows. All but the gathers vectorise; one loop that matched and summed pair by pair,
    with branches, took 1.6x as long. `camera` = (fx, fy, cx, cy), `limits` = (squared
    distance, cos angle), `robust` = (kernel code, threshold), `work` = _block_work()."""
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


@_allocating_loop
def _icp_loop(claims, parts, points, pose, to_model, mv, mn, camera, limits, robust, out):
    """Association + point-to-plane row + accumulation over the valid current points (6, n);
    out[c] collects chunk c's rows (slot NV-1: the chunk's valid current points). `robust` =
    host.robust_terms: the weights of the rows."""
    n = points.shape[1]
    chunks = out.shape[0]
    for c in claimed_items(claims, chunks, parts):
        acc = np.zeros(NV)
        work = _block_work(mv.dtype)
        pair_matrix = work[3].reshape((8, BLOCK))
        # Least squares weighs every row by 1: its rows are their own weighted rows.
        weighs = weighs_pairs(robust)
        weighted_matrix = work[4].reshape((7, BLOCK)) if weighs else pair_matrix
        start, stop = c * n // chunks, (c + 1) * n // chunks
        acc[NV - 1] += stop - start
        for block in range(start, stop, BLOCK):
            end = min(block + BLOCK, stop)
            _pair_rows_block(
                points, block, end, pose, to_model, mv, mn, camera, limits, robust, work
            )
            _add_block(acc, weighted_matrix, pair_matrix, end - block)
        out[c] = acc


@_allocating_loop
def _icp_pairs_loop(claims, parts, points, pose, to_model, mv, mn, camera, limits, out):
    """out[c] = (valid current points, ICP pairs) of chunk c: the counts of _icp_loop without
    its sums."""
    n = points.shape[1]
    chunks = out.shape[0]
    for c in claimed_items(claims, chunks, parts):
        work = _block_work(mv.dtype)
        kept = work[3][7 * BLOCK :]
        start, stop = c * n // chunks, (c + 1) * n // chunks
        pairs = 0.0
        for block in range(start, stop, BLOCK):
            end = min(block + BLOCK, stop)
            _pair_rows_block(
                points, block, end, pose, to_model, mv, mn, camera, limits, NO_WEIGHTS, work
            )
            pairs += kept[: end - block].sum()
        out[c, 0] = stop - start
        out[c, 1] = pairs


@_loop
def _associate_loop(
    claims, parts, points, normals, pose, to_model, mv, mn, camera, limits, keep, out
):
    for k in claimed_items(claims, points.shape[1], parts):
        point = (points[0, k], points[1, k], points[2, k])
        normal = (normals[0, k], normals[1, k], normals[2, k])
        kept, wx, wy, wz, qx, qy, qz, ux, uy, uz = icp_match(
            point, normal, pose, to_model, mv, mn, camera, limits
        )
        keep[k] = kept
        out[0, k], out[1, k], out[2, k] = wx, wy, wz
        out[3, k], out[4, k], out[5, k] = qx, qy, qz
        out[6, k], out[7, k], out[8, k] = ux, uy, uz


@_loop
def _point_to_plane_loop(claims, parts, world, mv, mn, jacobian, residuals):
    for k in claimed_items(claims, world.shape[1], parts):
        j0, j1, j2, j3, j4, j5, r = point_to_plane_row(
            (world[0, k], world[1, k], world[2, k]),
            (mv[0, k], mv[1, k], mv[2, k]),
            (mn[0, k], mn[1, k], mn[2, k]),
        )
        jacobian[0, k], jacobian[1, k], jacobian[2, k] = j0, j1, j2
        jacobian[3, k], jacobian[4, k], jacobian[5, k] = j3, j4, j5
        residuals[k] = r


@_loop
def _accumulate_loop(claims, parts, jacobian, residuals, weights, weighted, out):
    n = residuals.shape[0]
    chunks = out.shape[0]
    for c in claimed_items(claims, chunks, parts):
        acc = out[c]
        for k in range(c * n // chunks, (c + 1) * n // chunks):
            w = weights[k] if weighted else 1.0
            row = (
                jacobian[0, k],
                jacobian[1, k],
                jacobian[2, k],
                jacobian[3, k],
                jacobian[4, k],
                jacobian[5, k],
            )
            add_row(acc, row, residuals[k], w)


@_loop
def _interest_mask_loop(claims, parts, dx, dy, depth, g2, use_depth, max_depth, mask):
    for v in claimed_items(claims, dx.shape[0], parts):
        for u in range(dx.shape[1]):
            keep = is_interest(dx, dy, v, u, g2)
            if keep and use_depth:
                keep = has_depth(depth, v, u, max_depth)
            mask[v, u] = keep


@_loop
def _interest_data_loop(
    claims, parts, indices, depth, intensity, dx, dy, camera, points, values, grad
):
    width = depth.shape[1]
    for k in claimed_items(claims, indices.shape[0], parts):
        i = indices[k]
        v = i // width
        u = i - v * width
        points[0, k], points[1, k], points[2, k] = backproject(u, v, float(depth[v, u]), camera)
        values[k] = float(intensity[v, u])
        grad[0, k] = float(dx[v, u])
        grad[1, k] = float(dy[v, u])


@numba.njit(cache=True, error_model="numpy")
def _warp_block(points, start, stop, relative, camera, warp):
    """warp_project of points start:stop into warp's columns (x, y, z, u, v): branch-free, so
    it vectorises (divisions 8 at a time; rows read as slices, see _project_block)."""
    px, py, pz = points[0, start:stop], points[1, start:stop], points[2, start:stop]
    for i in range(stop - start):
        x, y, z, u, v = warp_project(relative, (px[i], py[i], pz[i]), camera)
        warp[0, i], warp[1, i], warp[2, i], warp[3, i], warp[4, i] = x, y, z, u, v


@_loop
def _correspond_loop(
    claims,
    parts,
    points,
    intensity,
    gradient,
    relative,
    pose,
    previous,
    warped,
    camera,
    max_change,
    pairs,
    sums,
    warps,
):
    """Algorithm 2 per interest point k: pairs[:, k] = (residual, NaN = not kept; world point;
    warped point; gradient), what J needs; sums[c] = (sum r^2, count) of chunk c for sigma'.
    Each block's warps first, in a loop that vectorises. `previous` = (depth, intensity, dx,
    dy) images of the previous frame; `warps` (threads, 5, BLOCK): each thread's work array."""
    depth, prev_i, prev_dx, prev_dy = previous
    n = pairs.shape[1]
    chunks = sums.shape[0]
    warp = warps[claim_slot(claims)]
    for c in claimed_items(claims, chunks, parts):
        start, stop = c * n // chunks, (c + 1) * n // chunks
        for block in range(start, stop, BLOCK):
            end = min(block + BLOCK, stop)
            _warp_block(points, block, end, relative, camera, warp)
            for k in range(block, end):
                i = k - block
                sample = (warp[0, i], warp[1, i], warp[2, i], warp[3, i], warp[4, i])
                ok, r, wx, wy, wz, x, y, z, gx, gy = warp_sample(
                    points,
                    intensity,
                    gradient,
                    k,
                    sample,
                    pose,
                    depth,
                    prev_i,
                    prev_dx,
                    prev_dy,
                    warped,
                    max_change,
                )
                pairs[0, k], pairs[1, k], pairs[2, k], pairs[3, k] = r, wx, wy, wz
                pairs[4, k], pairs[5, k], pairs[6, k] = x, y, z
                pairs[7, k], pairs[8, k] = gx, gy
                if ok:
                    sums[c, 0] += r * r
                    sums[c, 1] += 1.0


@_loop
def _photometric_loop(
    claims, parts, world, warped_points, gradient, previous_pose, focal, jacobian
):
    for k in claimed_items(claims, world.shape[1], parts):
        j0, j1, j2, j3, j4, j5 = photometric_row(
            (world[0, k], world[1, k], world[2, k]),
            (warped_points[0, k], warped_points[1, k], warped_points[2, k]),
            (gradient[0, k], gradient[1, k]),
            previous_pose,
            focal,
        )
        jacobian[0, k], jacobian[1, k], jacobian[2, k] = j0, j1, j2
        jacobian[3, k], jacobian[4, k], jacobian[5, k] = j3, j4, j5


@numba.njit(cache=True, error_model="numpy")
def _weighted_rows_block(pairs, start, stop, previous_pose, focal, sigma, rows):
    """photometric_row and the squared robust weight w of pairs[:, start:stop] (_correspond_loop's
    columns), branch-free so that it vectorises: rows[k * BLOCK + m] = (j0..j5, r, 1) for
    k = 0..7 and (w j0..w j5, w r) for k = 8..14 of a kept pair, zeros for a pair not kept (NaN
    r). rows is flat: with constant offsets LLVM sees one output region (a (7, BLOCK) array's 7
    rows were too many overlap checks for it)."""
    # the rows as slices indexed from 0 (see _project_block)
    r, wx, wy = pairs[0, start:stop], pairs[1, start:stop], pairs[2, start:stop]
    wz, x, y = pairs[3, start:stop], pairs[4, start:stop], pairs[5, start:stop]
    z, gx, gy = pairs[6, start:stop], pairs[7, start:stop], pairs[8, start:stop]
    for i in range(stop - start):
        j0, j1, j2, j3, j4, j5 = photometric_row(
            (wx[i], wy[i], wz[i]), (x[i], y[i], z[i]), (gx[i], gy[i]), previous_pose, focal
        )
        kept = not np.isnan(r[i])
        w = robust_weight(r[i], sigma)
        w = w * w
        residual = r[i] if kept else 0.0
        j0, j1, j2 = (j0, j1, j2) if kept else (0.0, 0.0, 0.0)
        j3, j4, j5 = (j3, j4, j5) if kept else (0.0, 0.0, 0.0)
        rows[i], rows[BLOCK + i], rows[2 * BLOCK + i] = j0, j1, j2
        rows[3 * BLOCK + i], rows[4 * BLOCK + i], rows[5 * BLOCK + i] = j3, j4, j5
        rows[6 * BLOCK + i], rows[7 * BLOCK + i] = residual, 1.0 if kept else 0.0
        rows[8 * BLOCK + i], rows[9 * BLOCK + i], rows[10 * BLOCK + i] = w * j0, w * j1, w * j2
        rows[11 * BLOCK + i], rows[12 * BLOCK + i] = w * j3, w * j4
        rows[13 * BLOCK + i], rows[14 * BLOCK + i] = w * j5, w * residual


@_allocating_loop
def _rgbd_rows_loop(claims, parts, pairs, previous_pose, focal, sigma, out):
    """Robustly weighted photometric rows of the kept pairs, summed per chunk (block by block:
    the rows, then their sums, each in a loop that vectorises)."""
    n = pairs.shape[1]
    chunks = out.shape[0]
    for c in claimed_items(claims, chunks, parts):
        acc = np.zeros(NV)
        rows = np.empty(15 * BLOCK)
        matrix = rows.reshape((15, BLOCK))
        start, stop = c * n // chunks, (c + 1) * n // chunks
        for block in range(start, stop, BLOCK):
            end = min(block + BLOCK, stop)
            _weighted_rows_block(pairs, block, end, previous_pose, focal, sigma, rows)
            _add_block(acc, matrix[8:], matrix[:8], end - block)
        out[c] = acc


# ----------------------------------------------------------------------------------------------
# Host helpers


@numba.njit(cache=True)
def _copy_maps(source, target):
    """target[...] = source for (h, w, 3) maps: NumPy copies a strided map 3 values at a time
    (0.37 ms for a 320x240 pyramid level), this unrolled loop in 0.08 ms."""
    for v in range(source.shape[0]):
        for u in range(source.shape[1]):
            target[v, u, 0] = source[v, u, 0]
            target[v, u, 1] = source[v, u, 1]
            target[v, u, 2] = source[v, u, 2]


def stage(array):
    """Arrays as the loops take them: C-contiguous NumPy (device arrays are downloaded). One
    layout means one compiled specialisation per loop (the model pyramid's strided levels are
    copied once per frame)."""
    if array is None:
        return None
    if hasattr(array, "copy_to_host") and not isinstance(array, np.ndarray):
        return array.copy_to_host()
    if array.ndim == 3 and array.shape[2] == 3 and not array.flags.c_contiguous:
        copy = np.empty(array.shape, dtype=array.dtype)
        _copy_maps(array, copy)
        return copy
    return np.ascontiguousarray(array)


def _run(loop, count: int, *args) -> None:
    """run_parallel a loop; below PARALLEL_MIN items on the calling thread alone. Waking the other
    threads costs more than such a loop, and on a busy machine a parallel loop waits for its
    slowest (descheduled) thread: tens of milliseconds per call were measured at load 9 on two
    cores for loops of a few thousand points."""
    run_parallel_above(PARALLEL_MIN, loop, count, *args)


def _partials(count: int) -> np.ndarray:
    return np.zeros((host.chunks_for(count, CHUNKS), NV))


# ----------------------------------------------------------------------------------------------
# ICP (kintinuous_ref.odometry.icp)


def valid_points(vertices, normals) -> np.ndarray:
    """The valid current points (finite vertex and normal) as (6, n) columns (px, py, pz, nx, ny,
    nz) in the reference's row-major order (ref `valid_points`), in the maps' own precision: the
    loops turn each value into float64 as they read it, as the reference does once for all, and
    float32 columns halve what every ICP iteration reads (level 0: ~13 -> ~6.5 MB). Depends on
    the frame only: the ICP problem computes it once per level, not per iteration."""
    counts = np.empty(vertices.shape[0], dtype=np.int64)
    _run(_valid_counts, vertices.shape[0] * vertices.shape[1], vertices, normals, counts)
    starts = np.zeros_like(counts)
    np.cumsum(counts[:-1], out=starts[1:])
    points = np.empty((6, int(counts.sum())), dtype=np.result_type(vertices, normals))
    _run(_compact_loop, vertices.shape[0] * vertices.shape[1], vertices, normals, starts, points)
    return points


def _run_on_points(
    loop,
    out,
    points,
    model_vertices,
    model_normals,
    pose,
    model_pose,
    camera,
    distance_threshold,
    angle_threshold_deg,
    model_inverse,
    *robust,
) -> None:
    """Run an ICP loop over the valid current points into `out` (its per-chunk rows); `robust`:
    host.robust_terms for the loops that weigh their rows."""
    host.check_map("model vertex map", model_vertices, camera)
    host.check_map("model normal map", model_normals, camera)
    pose, to_model, dist2, cos_min = host.icp_constants(
        pose, model_pose, distance_threshold, angle_threshold_deg, model_inverse
    )
    intrinsics = pinhole(camera)
    arguments = (pose, to_model, model_vertices, model_normals, intrinsics, (dist2, cos_min))
    _run(loop, points.shape[1], points, *arguments, *robust, out)


def icp_points_system(
    points,
    model_vertices,
    model_normals,
    pose,
    model_pose,
    camera,
    distance_threshold,
    angle_threshold_deg,
    model_inverse=None,
    robust_kernel="none",
    robust_threshold=0.0,
    model_noise=None,
) -> tuple[LinearSystem, int]:
    """icp_system of the valid current points (`valid_points`) and their number (for the inlier
    fraction); `model_inverse` as in host.icp_constants; `robust_threshold` the kernel's k or c
    in metres (ref icp.robust_threshold); `model_noise` as ref icp.pair_weights'."""
    out = _partials(points.shape[1])
    _run_on_points(
        _icp_loop,
        out,
        points,
        model_vertices,
        model_normals,
        pose,
        model_pose,
        camera,
        distance_threshold,
        angle_threshold_deg,
        model_inverse,
        host.robust_terms(robust_kernel, robust_threshold, model_noise),
    )
    return host.sum_partials(out)


def icp_points_pairs(
    points,
    model_vertices,
    model_normals,
    pose,
    model_pose,
    camera,
    distance_threshold,
    angle_threshold_deg,
    model_inverse=None,
    robust_kernel="none",
    robust_threshold=0.0,
    model_noise=None,
) -> tuple[int, int]:
    """icp_pairs of the valid current points (`valid_points`)."""
    out = np.zeros((host.chunks_for(points.shape[1], CHUNKS), 2))
    _run_on_points(
        _icp_pairs_loop,
        out,
        points,
        model_vertices,
        model_normals,
        pose,
        model_pose,
        camera,
        distance_threshold,
        angle_threshold_deg,
        model_inverse,
    )
    valid, pairs = out.sum(axis=0)
    return int(pairs), int(valid)


def icp_system_and_valid(
    vertices,
    normals,
    model_vertices,
    model_normals,
    pose,
    model_pose,
    camera,
    distance_threshold,
    angle_threshold_deg,
    robust_kernel="none",
    robust_threshold=0.0,
    model_noise=None,
) -> tuple[LinearSystem, int]:
    """icp_system and the number of valid current points (for the inlier fraction)."""
    host.check_map("current vertex map", vertices, camera)
    host.check_map("current normal map", normals, camera)
    return icp_points_system(
        valid_points(vertices, normals),
        model_vertices,
        model_normals,
        pose,
        model_pose,
        camera,
        distance_threshold,
        angle_threshold_deg,
        None,
        robust_kernel,
        robust_threshold,
        model_noise,
    )


def icp_system(
    vertices: np.ndarray,
    normals: np.ndarray,
    pose: np.ndarray,
    model_vertices: np.ndarray,
    model_normals: np.ndarray,
    model_pose: np.ndarray,
    camera: Intrinsics,
    distance_threshold: float = 0.10,
    angle_threshold_deg: float = 20.0,
    robust_kernel: str = "none",
    robust_noise: float = IcpConfig.robust_noise,
    model_noise: float | None = None,
) -> LinearSystem:
    """The 6x6 point-to-plane normal equations of one ICP iteration at one level: association,
    rows and sums in one pass over the current maps (nothing is stored per pair)."""
    return icp_system_and_valid(
        stage(vertices),
        stage(normals),
        stage(model_vertices),
        stage(model_normals),
        pose,
        model_pose,
        camera,
        distance_threshold,
        angle_threshold_deg,
        robust_kernel,
        robust_threshold(robust_kernel, robust_noise),
        model_noise,
    )[0]


def associate(
    points: np.ndarray,
    point_normals: np.ndarray,
    pose: np.ndarray,
    model_vertices: np.ndarray,
    model_normals: np.ndarray,
    model_pose: np.ndarray,
    camera: Intrinsics,
    distance_threshold: float,
    angle_threshold_deg: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Projective data association: (world point, model vertex, model normal) as (3, M) columns,
    in the reference's order. Model maps as (3, h*w) columns (ref map_columns)."""
    shape = (camera.height, camera.width, 3)
    host.check_image("model vertex columns", model_vertices, (3, camera.height * camera.width))
    host.check_image("model normal columns", model_normals, (3, camera.height * camera.width))
    pose, to_model, dist2, cos_min = host.icp_constants(
        pose, model_pose, distance_threshold, angle_threshold_deg
    )
    points = np.ascontiguousarray(points, dtype=np.float64)
    point_normals = np.ascontiguousarray(point_normals, dtype=np.float64)
    keep = np.empty(points.shape[1], dtype=np.bool_)
    out = np.empty((9, points.shape[1]))
    _run(
        _associate_loop,
        points.shape[1],
        points,
        point_normals,
        pose,
        to_model,
        np.ascontiguousarray(np.asarray(model_vertices).T.reshape(shape)),
        np.ascontiguousarray(np.asarray(model_normals).T.reshape(shape)),
        pinhole(camera),
        (dist2, cos_min),
        keep,
        out,
    )
    kept = np.compress(keep, out, axis=1)
    return kept[0:3], kept[3:6], kept[6:9]


def point_to_plane_rows(
    world: np.ndarray, model_vertices: np.ndarray, model_normals: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Jacobian (6, N) and residuals (N,) of the point-to-plane cost at xi = 0 (eq. 9)."""
    n = world.shape[1]
    jacobian = np.empty((6, n))
    residuals = np.empty(n)
    _run(
        _point_to_plane_loop,
        n,
        np.ascontiguousarray(world, dtype=np.float64),
        np.ascontiguousarray(model_vertices, dtype=np.float64),
        np.ascontiguousarray(model_normals, dtype=np.float64),
        jacobian,
        residuals,
    )
    return jacobian, residuals


# ----------------------------------------------------------------------------------------------
# Normal equations (kintinuous_ref.odometry.solve)


def accumulate(
    jacobian: np.ndarray, residuals: np.ndarray, weights: np.ndarray | None = None
) -> LinearSystem:
    """Normal equations of the (6, N) Jacobian and (N,) residuals in float64, chunked sums."""
    residuals = np.ascontiguousarray(residuals, dtype=np.float64)
    out = _partials(len(residuals))
    weighted = weights is not None
    _run(
        _accumulate_loop,
        len(residuals),
        np.ascontiguousarray(jacobian, dtype=np.float64),
        residuals,
        np.ascontiguousarray(weights, dtype=np.float64) if weighted else residuals,
        weighted,
        out,
    )
    return host.sum_partials(out)[0]


# ----------------------------------------------------------------------------------------------
# RGB-D (kintinuous_ref.odometry.rgbd)


def _interest_mask(dx, dy, depth, min_gradient, max_depth) -> np.ndarray:
    mask = np.empty(dx.shape, dtype=np.bool_)
    use_depth = depth is not None
    _run(
        _interest_mask_loop,
        dx.size,
        dx,
        dy,
        depth if use_depth else dx,
        float(min_gradient) ** 2,
        use_depth,
        float(max_depth),
        mask,
    )
    return mask


def interest_points(
    intensity_dx: np.ndarray, intensity_dy: np.ndarray, min_gradient: float
) -> np.ndarray:
    """Algorithm 1: flat indices (ascending) of the pixels with dx^2 + dy^2 >= g^2."""
    dx, dy = stage(intensity_dx), stage(intensity_dy)
    host.check_image("intensity_dy", dy, dx.shape)
    return np.flatnonzero(_interest_mask(dx, dy, None, min_gradient, 0.0))


def prepare_level(
    depth: np.ndarray,
    intensity: np.ndarray,
    intensity_dx: np.ndarray,
    intensity_dy: np.ndarray,
    camera: Intrinsics,
    min_gradient: float,
    max_depth: float,
) -> InterestPoints:
    """Interest points with valid depth and their 3D points, intensities and gradients."""
    depth, intensity = stage(depth), stage(intensity)
    dx, dy = stage(intensity_dx), stage(intensity_dy)
    shape = (camera.height, camera.width)
    for name, image in (("depth", depth), ("intensity", intensity), ("dx", dx), ("dy", dy)):
        host.check_image(f"current {name} image", image, shape)
    indices = np.flatnonzero(_interest_mask(dx, dy, depth, min_gradient, max_depth))
    n = len(indices)
    points, values, gradient = np.empty((3, n)), np.empty(n), np.empty((2, n))
    images = (indices, depth, intensity, dx, dy)
    _run(_interest_data_loop, n, *images, pinhole(camera), points, values, gradient)
    return InterestPoints(indices, points, values, gradient)


def _correspond_all(
    points,
    pose,
    previous_pose,
    previous_depth,
    previous_intensity,
    camera,
    max_depth_change,
    previous_dx,
    previous_dy,
):
    """Per interest point: ((9, n) pairs as _correspond_loop writes them, (sum r^2, count))."""
    previous_depth, previous_intensity = stage(previous_depth), stage(previous_intensity)
    shape = (camera.height, camera.width)
    host.check_image("previous depth image", previous_depth, shape)
    host.check_image("previous intensity image", previous_intensity, shape)
    warped = previous_dx is not None and previous_dy is not None
    prev_dx = stage(previous_dx) if warped else previous_intensity
    prev_dy = stage(previous_dy) if warped else previous_intensity
    n = points.points.shape[1]
    pairs = np.empty((9, n))
    sums = np.zeros((host.chunks_for(n, CHUNKS), 2))
    _run(
        _correspond_loop,
        n,
        np.ascontiguousarray(points.points, dtype=np.float64),
        np.ascontiguousarray(points.intensity, dtype=np.float64),
        np.ascontiguousarray(points.gradient, dtype=np.float64),
        host.relative_pose(pose, previous_pose),
        np.ascontiguousarray(pose, dtype=np.float64),
        (previous_depth, previous_intensity, prev_dx, prev_dy),
        warped,
        pinhole(camera),
        float(max_depth_change),
        pairs,
        sums,
        np.empty((threads(), 5, BLOCK)),
    )
    return pairs, sums.sum(axis=0)


def correspond(
    points: InterestPoints,
    pose: np.ndarray,
    previous_pose: np.ndarray,
    previous_depth: np.ndarray,
    previous_intensity: np.ndarray,
    camera: Intrinsics,
    max_depth_change: float,
    previous_dx: np.ndarray | None = None,
    previous_dy: np.ndarray | None = None,
) -> Correspondences:
    """Algorithm 2: the interest points warped into the previous frame (eq. 2) that pass the
    image and d_s tests, in the reference's order."""
    pairs, _ = _correspond_all(
        points,
        pose,
        previous_pose,
        previous_depth,
        previous_intensity,
        camera,
        max_depth_change,
        previous_dx,
        previous_dy,
    )
    kept = np.flatnonzero(~np.isnan(pairs[0]))
    columns = np.take(pairs, kept, axis=1)
    return Correspondences(
        np.ascontiguousarray(columns[1:4]),
        np.ascontiguousarray(columns[4:7]),
        columns[0].copy(),
        np.ascontiguousarray(columns[7:9]),
        kept,
    )


def photometric_rows(
    correspondences: Correspondences, previous_pose: np.ndarray, camera: Intrinsics
) -> tuple[np.ndarray, np.ndarray]:
    """Unweighted Jacobian (6, N) and residuals (N,) of the intensity differences at xi = 0."""
    n = correspondences.world.shape[1]
    jacobian = np.empty((6, n))
    _run(
        _photometric_loop,
        n,
        np.ascontiguousarray(correspondences.world, dtype=np.float64),
        np.ascontiguousarray(correspondences.warped, dtype=np.float64),
        np.ascontiguousarray(correspondences.gradient, dtype=np.float64),
        np.ascontiguousarray(previous_pose, dtype=np.float64),
        (float(camera.fx), float(camera.fy)),
        jacobian,
    )
    return jacobian, correspondences.residuals


def rgbd_system(
    points: InterestPoints,
    pose: np.ndarray,
    previous_pose: np.ndarray,
    previous_depth: np.ndarray,
    previous_intensity: np.ndarray,
    camera: Intrinsics,
    max_depth_change: float = 0.07,
    previous_dx: np.ndarray | None = None,
    previous_dy: np.ndarray | None = None,
) -> LinearSystem:
    """The 6x6 normal equations of one RGB-D iteration at one level, robustly weighted: pass 1
    finds the pairs and sum r^2 (sigma'), pass 2 sums the weighted rows."""
    pairs, (squares, count) = _correspond_all(
        points,
        pose,
        previous_pose,
        previous_depth,
        previous_intensity,
        camera,
        max_depth_change,
        previous_dx,
        previous_dy,
    )
    if count == 0:
        return LinearSystem.empty()
    sigma = float(np.sqrt(squares / count))
    out = _partials(pairs.shape[1])
    _run(
        _rgbd_rows_loop,
        pairs.shape[1],
        pairs,
        np.ascontiguousarray(previous_pose, dtype=np.float64),
        (float(camera.fx), float(camera.fy)),
        sigma,
        out,
    )
    return host.sum_partials(out)[0]


# ----------------------------------------------------------------------------------------------
# Per-frame problems


class IcpProblem(host.IcpProblemBase):
    """kintinuous_ref.odometry.icp.IcpProblem with the CPU loops underneath; each level's valid
    current points are compacted once, on first use, for all of its iterations."""

    def system_and_valid(self, level: int, pose: np.ndarray) -> tuple[LinearSystem, int]:
        return self._on_points(icp_points_system, level, pose)

    def inlier_fraction(self, pose: np.ndarray, level: int = 0) -> float:
        """As the base class, from the pair count alone (icp_points_pairs): no sums for this
        one look."""
        pairs, valid = self._on_points(icp_points_pairs, level, pose)
        return pairs / valid if valid else 0.0

    def _on_points(self, function, level: int, pose: np.ndarray):  # noqa: ANN001, ANN202
        """function(level's valid current points, model maps, pose, ...)."""
        vertices, normals, model_vertices, model_normals = self.maps(level)
        camera = self.current_levels[level].camera
        if level not in self._points:
            host.check_map("current vertex map", vertices, camera)
            host.check_map("current normal map", normals, camera)
            self._points[level] = valid_points(vertices, normals)
        return function(
            self._points[level],
            model_vertices,
            model_normals,
            pose,
            self.model_pose,
            camera,
            self.distance_threshold,
            self.angle_threshold_deg,
            self.model_inverse,
            self.robust_kernel,
            self.robust_threshold,
            self.model_noise,
        )


class RgbdProblem(host.RgbdProblemBase):
    """kintinuous_ref.odometry.rgbd.RgbdProblem with the CPU loops underneath."""


IcpProblem.kernels = RgbdProblem.kernels = sys.modules[__name__]


class DenseTracker(host.FastDenseTracker):
    """kintinuous_ref.odometry.DenseTracker with the CPU loops underneath."""

    def __init__(self, method: str, config: Config, camera: Intrinsics) -> None:
        super().__init__(method, config, camera, sys.modules[__name__])


def make_tracker(method: str, config: Config, camera: Intrinsics) -> Tracker:
    """kintinuous_ref.odometry.make_tracker (every method) with the CPU loops underneath."""
    return host.make_tracker_with(sys.modules[__name__], method, config, camera)
