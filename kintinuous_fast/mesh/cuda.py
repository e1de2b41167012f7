# ruff: noqa: ANN001  (numba kernels: argument types come from the call)
"""kintinuous_ref.marching_cubes as CUDA kernels: kintinuous_fast.mesh.ops's three passes, one
thread per row of voxels, with the prefix sum of the rows' counts on the device, so the counts
never cross to the host: only the two totals (to size the outputs), the vertices and the
triangles come back. The same vertices and triangles, in the same order, as the reference.
"""

from __future__ import annotations

import numpy as np
from numba import cuda

from kintinuous_fast.mesh.ops import build_ops
from kintinuous_fast.targets import cuda_device_jit, to_host
from kintinuous_fast.targets.cuda import BLOCK_1D, grid_1d, kernel, to_device

__all__ = ["marching_cubes"]

_ops = build_ops(cuda_device_jit())
row_vertices, row_triangles = _ops.row_vertices, _ops.row_triangles
row_is_uniform = _ops.row_is_uniform
write_row_vertices, write_row_triangles = _ops.write_row_vertices, _ops.write_row_triangles

# Threads of the one block per count that adds up the rows' counts.
SCAN_THREADS = 256


@kernel
def _count_kernel(tsdf, weight, min_weight, counts):
    row = cuda.grid(1)
    ny = tsdf.shape[1]
    if row < tsdf.shape[0] * ny and row_is_uniform(tsdf, row // ny, row % ny):
        counts[0, row] = counts[1, row] = 0
    elif row < tsdf.shape[0] * ny:
        counts[0, row] = row_vertices(tsdf, weight, min_weight, row // ny, row % ny)
        counts[1, row] = row_triangles(tsdf, weight, min_weight, row // ny, row % ny)


@kernel
def _scan_kernel(counts, starts):
    """starts[c, r + 1] = counts[c, 0] + ... + counts[c, r], block c for count c: each thread
    adds up one run of rows, the block scans the runs' sums (Hillis and Steele), then each
    thread writes its run's prefix sums."""
    channel, thread = cuda.blockIdx.x, cuda.threadIdx.x
    rows = counts.shape[1]
    run = (rows + SCAN_THREADS - 1) // SCAN_THREADS
    lo = min(thread * run, rows)
    hi = min(lo + run, rows)
    total = 0
    for row in range(lo, hi):
        total += counts[channel, row]
    sums = cuda.shared.array(SCAN_THREADS, np.int64)
    sums[thread] = total
    cuda.syncthreads()
    step = 1
    while step < SCAN_THREADS:
        below = sums[thread - step] if thread >= step else 0
        cuda.syncthreads()
        sums[thread] += below
        cuda.syncthreads()
        step *= 2
    running = sums[thread] - total
    if thread == 0:
        starts[channel, 0] = 0
    for row in range(lo, hi):
        running += counts[channel, row]
        starts[channel, row + 1] = running


@kernel
def _vertex_kernel(tsdf, weight, min_weight, starts, vertices, ids):
    row = cuda.grid(1)
    ny = tsdf.shape[1]
    if row < tsdf.shape[0] * ny and starts[row + 1] > starts[row]:
        out = (vertices, ids)
        write_row_vertices(tsdf, weight, min_weight, row // ny, row % ny, starts[row], out)


@kernel
def _triangle_kernel(tsdf, weight, min_weight, starts, triangles, ids, row_starts):
    row = cuda.grid(1)
    ny = tsdf.shape[1]
    if row < tsdf.shape[0] * ny and starts[row + 1] > starts[row]:
        found = (triangles, ids, row_starts)
        write_row_triangles(tsdf, weight, min_weight, row // ny, row % ny, starts[row], found)


def marching_cubes(tsdf, weight, min_weight: float) -> tuple[np.ndarray, np.ndarray]:
    """kintinuous_ref.marching_cubes.marching_cubes on the GPU, for host or device float32
    arrays: (vertices (V, 3) float64 in voxel coordinates, triangles (T, 3) int64) on the host,
    identical to the reference's."""
    if min(tsdf.shape) < 2:
        return np.zeros((0, 3), dtype=np.float64), np.zeros((0, 3), dtype=np.int64)
    tsdf, weight = to_device(tsdf, np.float32), to_device(weight, np.float32)
    rows = tsdf.shape[0] * tsdf.shape[1]
    grid, limit = grid_1d(rows), float(min_weight)
    counts = cuda.device_array((2, rows), dtype=np.int64)
    _count_kernel[grid, BLOCK_1D](tsdf, weight, limit, counts)
    starts = cuda.device_array((2, rows + 1), dtype=np.int64)
    _scan_kernel[2, SCAN_THREADS](counts, starts)
    vertex_count, triangle_count = (int(n) for n in to_host(starts[:, rows]))
    vertices = cuda.device_array((max(vertex_count, 1), 3), dtype=np.float64)
    ids = cuda.device_array(max(vertex_count, 1), dtype=np.int64)
    _vertex_kernel[grid, BLOCK_1D](tsdf, weight, limit, starts[0], vertices, ids)
    triangles = cuda.device_array((max(triangle_count, 1), 3), dtype=np.int64)
    found = (starts[1], triangles, ids, starts[0])
    _triangle_kernel[grid, BLOCK_1D](tsdf, weight, limit, *found)
    return to_host(vertices)[:vertex_count], to_host(triangles)[:triangle_count]
