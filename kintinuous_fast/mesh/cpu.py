# ruff: noqa: ANN001  (numba loops: argument types come from the call)
"""kintinuous_ref.marching_cubes on the CPU: kintinuous_fast.mesh.ops's trimmed passes over the
rows of voxels, each a loop run on all threads; the same vertices and triangles, in the same
order, as the reference.

1. each row of voxels' trim (its first and last crossed z edge, its end voxels' signs): the one
   pass that reads the whole TSDF;
2. each row of cubes' range from its four rows' trims, and where its entries go (one thread:
   a few operations per row);
3. the entries (case and used edges) of the cubes in the ranges, and each row's triangle count;
4. each row's vertex count, from the entries of the rows of cubes around it;
5. prefix sums of the counts, then each row's vertices, then each row's triangles.
"""

from __future__ import annotations

from pathlib import Path

import numba
import numpy as np

from kintinuous_fast.mesh.ops import build_ops
from kintinuous_fast.targets import cpu_jit_numpy_errors
from kintinuous_fast.targets.cache import drop_stale_kernels
from kintinuous_fast.targets.cpu import claimed_items, parallel_part, run_parallel, threads
from kintinuous_fast.tsdf.volume import FastTsdfVolume, slab_view
from kintinuous_ref.box_surface import BoxSurface, box_surface
from kintinuous_ref.tsdf import TsdfVolume

__all__ = ["marching_cubes", "mesh_box"]

_ops = build_ops(cpu_jit_numpy_errors)
row_trim, cube_row_range = _ops.row_trim, _ops.cube_row_range
cube_row_entries = _ops.cube_row_entries
mark_owned, write_owned_vertices = _ops.mark_owned, _ops.write_owned_vertices
write_entry_triangles = _ops.write_entry_triangles

# Parts each pass is cut into per thread: the surface lies in few rows, so many small parts
# keep the threads even.
PARTS_PER_THREAD = 32


@parallel_part(error_model="numpy")
def _trim_loop(claims, parts, tsdf, trims):
    ny = tsdf.shape[1]
    for row in claimed_items(claims, tsdf.shape[0] * ny, parts):
        trims[row, 0], trims[row, 1], trims[row, 2] = row_trim(tsdf, row // ny, row % ny)


@numba.njit(nogil=True, cache=True, error_model="numpy", _nrt=False)
def _cube_ranges(trims, shape, ranges, owners):
    """ranges[row] = (lo, hi, index of the first entry) of each row of cubes, and owners[row]
    = (lo, hi, index of the first) of each row of voxels' span that can own vertices (the
    ranges of the up to four rows of cubes around it, each one voxel longer); returns the
    numbers of entries and of owned spans' voxels."""
    at = 0
    for row in range(shape[0] * shape[1]):
        lo, hi = cube_row_range(trims, shape, row // shape[1], row % shape[1])
        if lo > hi:
            lo, hi = 0, -1
        ranges[row, 0], ranges[row, 1], ranges[row, 2] = lo, hi, at
        at += hi - lo + 1
    owned = 0
    for row in range(shape[0] * shape[1]):
        i, j = row // shape[1], row % shape[1]
        lo, hi = shape[2], -1
        for corner in range(4):
            ci, cj = i - (corner & 1), j - (corner >> 1)
            cube_row = ci * shape[1] + cj
            if ci >= 0 and cj >= 0 and ranges[cube_row, 0] <= ranges[cube_row, 1]:
                lo, hi = min(lo, ranges[cube_row, 0]), max(hi, ranges[cube_row, 1] + 1)
        if lo > hi:
            lo, hi = 0, -1
        owners[row, 0], owners[row, 1], owners[row, 2] = lo, hi, owned
        owned += hi - lo + 1
    return at, owned


@parallel_part(error_model="numpy")
def _entry_loop(claims, parts, tsdf, weight, min_weight, ranges, entries, triangles):
    ny = tsdf.shape[1]
    for row in claimed_items(claims, tsdf.shape[0] * ny, parts):
        span = (ranges[row, 0], ranges[row, 1], ranges[row, 2])
        if span[0] > span[1]:
            triangles[row], ranges[row, 3], ranges[row, 4] = 0, 0, -1
            continue
        i, j = row // ny, row % ny
        found = cube_row_entries(tsdf, weight, min_weight, i, j, span, entries)
        triangles[row], ranges[row, 3], ranges[row, 4] = found


@parallel_part(error_model="numpy")
def _vertex_count_loop(claims, parts, shape, ranges, entries, found, vertices):
    ny = shape[1]
    owners = found[0]
    for row in claimed_items(claims, shape[0] * ny, parts):
        vertices[row] = 0
        if owners[row, 0] <= owners[row, 1]:
            vertices[row] = mark_owned(ranges, entries, shape, row // ny, row % ny, found)


@parallel_part(error_model="numpy")
def _vertex_loop(claims, parts, tsdf, weight, min_weight, spans, starts, vertices, ids):
    ny = tsdf.shape[1]
    ranges, owners, owned = spans
    for row in claimed_items(claims, tsdf.shape[0] * ny, parts):
        if starts[row + 1] > starts[row]:
            found, out = (ranges, owners, owned, starts[row]), (vertices, ids)
            write_owned_vertices(tsdf, weight, min_weight, found, row // ny, row % ny, out)


@parallel_part(error_model="numpy")
def _triangle_loop(claims, parts, shape, ranges, entries, starts, triangles, ids, row_starts):
    ny = shape[1]
    for row in claimed_items(claims, shape[0] * ny, parts):
        if starts[row + 1] > starts[row]:
            span = (ranges[row, 3], ranges[row, 4], ranges[row, 2] - ranges[row, 0], starts[row])
            found = (triangles, ids, row_starts)
            write_entry_triangles(shape, span, entries, row // ny, row % ny, found)


def marching_cubes(
    tsdf: np.ndarray, weight: np.ndarray, min_weight: float
) -> tuple[np.ndarray, np.ndarray]:
    """kintinuous_ref.marching_cubes.marching_cubes: (vertices (V, 3) float64 in voxel
    coordinates, triangles (T, 3) int64), identical to the reference's."""
    tsdf = np.ascontiguousarray(tsdf, dtype=np.float32)
    weight = np.ascontiguousarray(weight, dtype=np.float32)
    if min(tsdf.shape) < 2:
        return np.zeros((0, 3), dtype=np.float64), np.zeros((0, 3), dtype=np.int64)
    parts = PARTS_PER_THREAD * threads()
    shape, limit = np.array(tsdf.shape, dtype=np.int64), float(min_weight)
    rows = tsdf.shape[0] * tsdf.shape[1]
    trims = np.empty((rows, 3), dtype=np.int64)
    run_parallel(_trim_loop, tsdf, trims, parts=parts)
    ranges, owners = np.empty((rows, 5), dtype=np.int64), np.empty((rows, 3), dtype=np.int64)
    sizes = _cube_ranges(trims, shape, ranges, owners)
    entries = np.empty(max(sizes[0], 1), dtype=np.int32)
    owned = np.empty(max(sizes[1], 1), dtype=np.uint8)
    counts = np.empty((2, rows), dtype=np.int64)
    run_parallel(_entry_loop, tsdf, weight, limit, ranges, entries, counts[1], parts=parts)
    found = (owners, owned)
    run_parallel(_vertex_count_loop, shape, ranges, entries, found, counts[0], parts=parts)
    starts = np.zeros((2, rows + 1), dtype=np.int64)
    np.cumsum(counts, axis=1, out=starts[:, 1:])
    vertices = np.empty((starts[0, -1], 3), dtype=np.float64)
    ids = np.empty(starts[0, -1], dtype=np.int64)
    found = ((ranges, owners, owned), starts[0], vertices, ids)
    run_parallel(_vertex_loop, tsdf, weight, limit, *found, parts=parts)
    triangles = np.empty((starts[1, -1], 3), dtype=np.int64)
    found = (ranges, entries, starts[1], triangles, ids, starts[0])
    run_parallel(_triangle_loop, shape, *found, parts=parts)
    return vertices, triangles


def mesh_box(
    volume: TsdfVolume | FastTsdfVolume,
    lo: tuple[int, int, int],
    hi: tuple[int, int, int],
    min_weight: float,
) -> BoxSurface:
    """kintinuous_ref.marching_cubes.mesh_box with these loops' marching cubes: the surface of
    the logical box [lo, hi) by the slices' rules (kintinuous_ref.box_surface, in NumPy: per
    vertex, little work beside the marching cubes). A fast volume is read through its
    SlabView (the box's cells, dequantised)."""
    if isinstance(volume, FastTsdfVolume):
        volume = slab_view(volume)
    return box_surface(volume, lo, hi, min_weight, marching_cubes)


# numba checks a cached loop against its own file only, and these inline mesh/ops.py: the
# loops' cache goes when any source of the package changed (targets/cache.py's rule).
drop_stale_kernels([Path(_trim_loop.stats.cache_path)])
