# ruff: noqa: ANN001  (numba loops: argument types come from the call)
"""kintinuous_ref.marching_cubes on the CPU: kintinuous_fast.mesh.ops's three passes over the
rows of voxels, each a loop run on all threads; the same vertices and triangles, in the same
order, as the reference.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from kintinuous_fast.mesh.ops import build_ops
from kintinuous_fast.targets import cpu_jit_numpy_errors
from kintinuous_fast.targets.cache import drop_stale_kernels
from kintinuous_fast.targets.cpu import claimed_items, parallel_part, run_parallel

__all__ = ["marching_cubes"]

_ops = build_ops(cpu_jit_numpy_errors)
row_vertices, row_triangles = _ops.row_vertices, _ops.row_triangles
row_is_uniform = _ops.row_is_uniform
write_row_vertices, write_row_triangles = _ops.write_row_vertices, _ops.write_row_triangles


@parallel_part(error_model="numpy")
def _count_loop(claims, parts, tsdf, weight, min_weight, vertices, triangles):
    ny = tsdf.shape[1]
    for row in claimed_items(claims, tsdf.shape[0] * ny, parts):
        i, j = row // ny, row % ny
        if row_is_uniform(tsdf, i, j):
            vertices[row] = triangles[row] = 0
            continue
        vertices[row] = row_vertices(tsdf, weight, min_weight, i, j)
        triangles[row] = row_triangles(tsdf, weight, min_weight, i, j)


@parallel_part(error_model="numpy")
def _vertex_loop(claims, parts, tsdf, weight, min_weight, starts, vertices, ids):
    ny = tsdf.shape[1]
    for row in claimed_items(claims, tsdf.shape[0] * ny, parts):
        if starts[row + 1] > starts[row]:
            out = (vertices, ids)
            write_row_vertices(tsdf, weight, min_weight, row // ny, row % ny, starts[row], out)


@parallel_part(error_model="numpy")
def _triangle_loop(claims, parts, tsdf, weight, min_weight, starts, triangles, ids, row_starts):
    ny = tsdf.shape[1]
    for row in claimed_items(claims, tsdf.shape[0] * ny, parts):
        if starts[row + 1] > starts[row]:
            found = (triangles, ids, row_starts)
            write_row_triangles(tsdf, weight, min_weight, row // ny, row % ny, starts[row], found)


def marching_cubes(
    tsdf: np.ndarray, weight: np.ndarray, min_weight: float
) -> tuple[np.ndarray, np.ndarray]:
    """kintinuous_ref.marching_cubes.marching_cubes: (vertices (V, 3) float64 in voxel
    coordinates, triangles (T, 3) int64), identical to the reference's."""
    tsdf = np.ascontiguousarray(tsdf, dtype=np.float32)
    weight = np.ascontiguousarray(weight, dtype=np.float32)
    if min(tsdf.shape) < 2:
        return np.zeros((0, 3), dtype=np.float64), np.zeros((0, 3), dtype=np.int64)
    rows = tsdf.shape[0] * tsdf.shape[1]
    counts = np.zeros((2, rows), dtype=np.int64)
    run_parallel(_count_loop, tsdf, weight, float(min_weight), counts[0], counts[1])
    starts = np.zeros((2, rows + 1), dtype=np.int64)
    np.cumsum(counts, axis=1, out=starts[:, 1:])
    vertices = np.empty((starts[0, -1], 3), dtype=np.float64)
    ids = np.empty(starts[0, -1], dtype=np.int64)
    run_parallel(_vertex_loop, tsdf, weight, float(min_weight), starts[0], vertices, ids)
    triangles = np.empty((starts[1, -1], 3), dtype=np.int64)
    arguments = (starts[1], triangles, ids, starts[0])
    run_parallel(_triangle_loop, tsdf, weight, float(min_weight), *arguments)
    return vertices, triangles


# numba checks a cached loop against its own file only, and these inline mesh/ops.py: the
# loops' cache goes when any source of the package changed (targets/cache.py's rule).
drop_stale_kernels([Path(_count_loop.stats.cache_path)])
