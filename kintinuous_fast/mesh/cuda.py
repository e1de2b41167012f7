# ruff: noqa: ANN001  (numba kernels: argument types come from the call)
"""kintinuous_ref.marching_cubes as CUDA kernels: kintinuous_fast.mesh.ops's three passes, one
thread per row of voxels, with the prefix sum of the rows' counts on the device, so the counts
never cross to the host: only the two totals (to size the outputs), the vertices and the
triangles come back. The same vertices and triangles, in the same order, as the reference.

mesh_box meshes a box of a FastTsdfVolume where it lies, for the moving volume's slices:
1. the box's cells (wrapping around the cyclical buffer) dequantised into float32 TSDF and
   weight arrays of the box's shape, on the device;
2. the three passes of marching cubes on them (the totals come back: 16 bytes);
3. per vertex, the slices' edge rule (both voxels of its edge observed), per triangle whether
   its three vertices are kept (marking the vertices it uses), and a prefix sum of each;
4. the kept vertices, with their colours read from the colour volume, and the kept triangles,
   renumbered, written packed (their totals come back: 16 bytes, then the three arrays).
Only the surface crosses to the host: 24 bytes a vertex (+ 3 with a colour volume), 24 a
triangle, and 32 bytes of totals. The host names each vertex's grid edge from its coordinates
(box_surface.vertex_edges, on the V vertices).
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numba import cuda

from kintinuous_fast.mesh.ops import build_ops
from kintinuous_fast.mesh.slice_ops import build_slice_ops
from kintinuous_fast.targets import cuda_device_jit, to_host
from kintinuous_fast.targets.cuda import BLOCK_1D, grid_1d, kernel, to_device
from kintinuous_fast.tsdf.volume import FastTsdfVolume, SlabView
from kintinuous_ref.box_surface import BoxSurface, no_surface, vertex_edges

__all__ = ["marching_cubes", "mesh_box"]

_ops = build_ops(cuda_device_jit())
_slice = build_slice_ops(cuda_device_jit())
read_box_voxel, vertex_edge = _slice.read_box_voxel, _slice.vertex_edge
vertex_kept, write_vertex_colour = _slice.vertex_kept, _slice.write_vertex_colour
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
    empty = np.zeros((0, 3), dtype=np.float64), np.zeros((0, 3), dtype=np.int64)
    if min(tsdf.shape) < 2:
        return empty
    tsdf, weight = to_device(tsdf, np.float32), to_device(weight, np.float32)
    vertices, triangles, counts = _device_marching_cubes(tsdf, weight, min_weight)
    if counts[1] == 0:
        return empty
    return to_host(vertices[: counts[0]]), to_host(triangles[: counts[1]])


def _device_marching_cubes(tsdf, weight, min_weight: float) -> tuple[Any, Any, tuple[int, int]]:
    """marching_cubes of device arrays (every side >= 2), left on the device: (vertices (V, 3)
    float64, triangles (T, 3) int64, (V, T)), the arrays at least one row long and valid in
    their first V and T rows; the two totals (16 bytes) are the one download."""
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
    return vertices, triangles, (vertex_count, triangle_count)


# ----------------------------------------------------------------------------------------------
# A box of a volume, meshed on the device (the moving volume's slices)


@kernel
def _read_box_kernel(packed, box, tsdf, weight):
    """Row (i, j) of the box's voxels into the float32 arrays tsdf and weight (read_box_voxel)."""
    row = cuda.grid(1)
    ny = tsdf.shape[1]
    if row < tsdf.shape[0] * ny:
        for k in range(tsdf.shape[2]):
            read_box_voxel(packed, box, (row // ny, row % ny, k), (tsdf, weight))


@kernel
def _vertex_rule_kernel(vertices, count, weight, min_weight, kept, used):
    """kept[v] = 1 where both voxels of vertex v's edge reach min_weight; used[0, v] = 0."""
    v = cuda.grid(1)
    if v < count:
        edge = vertex_edge(vertices, v, weight.shape)
        kept[v] = 1 if vertex_kept(weight, edge, min_weight) else 0
        used[0, v] = 0


@kernel
def _triangle_rule_kernel(triangles, count, kept, triangle_kept, used):
    """triangle_kept[0, t] = 1 where triangle t's three vertices are kept, and then used[0, v]
    = 1 for each of them (threads that mark one vertex write the same value)."""
    t = cuda.grid(1)
    if t < count:
        a, b, c = triangles[t, 0], triangles[t, 1], triangles[t, 2]
        keep = kept[a] != 0 and kept[b] != 0 and kept[c] != 0
        triangle_kept[0, t] = 1 if keep else 0
        if keep:
            used[0, a] = used[0, b] = used[0, c] = 1


@kernel
def _totals_kernel(vertex_starts, triangle_starts, totals):
    """totals = (kept vertices, kept triangles): the prefix sums' last entries, one download."""
    if cuda.grid(1) == 0:
        totals[0] = vertex_starts[0, vertex_starts.shape[1] - 1]
        totals[1] = triangle_starts[0, triangle_starts.shape[1] - 1]


@kernel
def _pack_vertices_kernel(vertices, count, kept_at, box, colour, out, colours):
    """Each used vertex v (kept_at = (used, new indices)): its coordinates into out[its index]
    and its colour into colours[its index], for box = (lo, offsets, N, the box's shape) and
    colour = (colour volume, whether there is one; black without)."""
    v = cuda.grid(1)
    used, starts = kept_at
    if v < count and used[0, v] != 0:
        at = starts[0, v]
        out[at, 0], out[at, 1], out[at, 2] = vertices[v, 0], vertices[v, 1], vertices[v, 2]
        if colour[1]:
            edge = vertex_edge(vertices, v, box[3])
            write_vertex_colour(colour[0], (box[0], box[1], box[2]), edge, colours, at)
        else:
            colours[at, 0] = colours[at, 1] = colours[at, 2] = 0


@kernel
def _pack_triangles_kernel(triangles, count, triangle_kept, triangle_starts, vertex_starts, out):
    """Each kept triangle t into out[its new index], its corners renumbered to the kept
    vertices' new indices."""
    t = cuda.grid(1)
    if t < count and triangle_kept[0, t] != 0:
        at = triangle_starts[0, t]
        for corner in range(3):
            out[at, corner] = vertex_starts[0, triangles[t, corner]]


def mesh_box(
    volume: FastTsdfVolume | SlabView,
    lo: tuple[int, int, int],
    hi: tuple[int, int, int],
    min_weight: float,
) -> BoxSurface:
    """kintinuous_ref.marching_cubes.mesh_box on the GPU for a FastTsdfVolume in device memory
    (or the moving volume's SlabView of one): the surface of the logical box [lo, hi) by the
    slices' rules, meshed where the volume lies; only the surface is downloaded (module
    docstring). Identical to the reference's rules on the same fast volume."""
    fast = volume.fast if isinstance(volume, SlabView) else volume
    shape = tuple(int(b) - int(a) for a, b in zip(lo, hi, strict=True))
    if min(shape) < 2:
        return no_surface()
    box = (tuple(int(x) for x in lo), fast.offsets(), int(fast.resolution))
    tsdf = cuda.device_array(shape, dtype=np.float32)
    weight = cuda.device_array(shape, dtype=np.float32)
    packed = to_device(fast.tsdf_weight, np.int16)
    _read_box_kernel[grid_1d(shape[0] * shape[1]), BLOCK_1D](packed, box, tsdf, weight)
    below = float(np.nextafter(min_weight, -np.inf))  # weight >= m: weight > the float below m
    vertices, triangles, (vertex_count, triangle_count) = _device_marching_cubes(
        tsdf, weight, below
    )
    if triangle_count == 0:
        return no_surface()
    kept = _kept_surface(vertices, triangles, (vertex_count, triangle_count), weight, min_weight)
    return _download_surface(fast, box, shape, (vertices, triangles), kept)


def _kept_surface(vertices, triangles, counts: tuple[int, int], weight, min_weight: float):
    """(used vertices (1, V) and their new indices (1, V + 1), kept triangles (1, T) and their
    new indices (1, T + 1), the two totals on the host) of the slices' edge rule."""
    vertex_count, triangle_count = counts
    kept = cuda.device_array(vertex_count, dtype=np.uint8)
    used = cuda.device_array((1, vertex_count), dtype=np.int64)
    # NumPy compares the reference's float32 weights with a Python float in float32.
    limit = np.float32(min_weight)
    _vertex_rule_kernel[grid_1d(vertex_count), BLOCK_1D](
        vertices, vertex_count, weight, limit, kept, used
    )
    triangle_kept = cuda.device_array((1, triangle_count), dtype=np.int64)
    _triangle_rule_kernel[grid_1d(triangle_count), BLOCK_1D](
        triangles, triangle_count, kept, triangle_kept, used
    )
    vertex_starts = cuda.device_array((1, vertex_count + 1), dtype=np.int64)
    _scan_kernel[1, SCAN_THREADS](used, vertex_starts)
    triangle_starts = cuda.device_array((1, triangle_count + 1), dtype=np.int64)
    _scan_kernel[1, SCAN_THREADS](triangle_kept, triangle_starts)
    totals = cuda.device_array(2, dtype=np.int64)
    _totals_kernel[1, 1](vertex_starts, triangle_starts, totals)
    totals = tuple(int(n) for n in to_host(totals))
    return (used, vertex_starts), (triangle_kept, triangle_starts), totals


def _download_surface(fast: FastTsdfVolume, box: tuple, shape: tuple, surface: tuple, kept):
    """The kept vertices, triangles and colours packed on the device and downloaded, with the
    vertices' grid edges named on the host: the BoxSurface."""
    vertices, triangles = surface
    (used, vertex_starts), (triangle_kept, triangle_starts), (vertex_total, triangle_total) = kept
    if triangle_total == 0:
        return no_surface()
    out = cuda.device_array((vertex_total, 3), dtype=np.float64)
    colours = cuda.device_array((vertex_total, 3), dtype=np.uint8)
    has_colour = fast.colour is not None
    colour = to_device(fast.colour if has_colour else np.zeros((1, 1, 1, 4), np.uint8), np.uint8)
    _pack_vertices_kernel[grid_1d(used.shape[1]), BLOCK_1D](
        vertices,
        used.shape[1],
        (used, vertex_starts),
        (*box, shape),
        (colour, has_colour),
        out,
        colours,
    )
    packed = cuda.device_array((triangle_total, 3), dtype=np.int64)
    _pack_triangles_kernel[grid_1d(triangle_kept.shape[1]), BLOCK_1D](
        triangles, triangle_kept.shape[1], triangle_kept, triangle_starts, vertex_starts, packed
    )
    local = to_host(out)
    axis, lower, _ = vertex_edges(local, shape)
    return BoxSurface(
        vertices=local,
        triangles=to_host(packed),
        colours=to_host(colours) if has_colour else np.zeros((vertex_total, 3), np.uint8),
        edges=np.column_stack([lower, axis]),
    )
