"""Marching cubes (kintinuous_ref.marching_cubes) one row at a time, written once for the CPU and
the CUDA target: a row is the line of voxels (i, j, 0..nz-1) with the three edges that start at
each of them and, where i < nx - 1 and j < ny - 1, the line of cubes with those lower voxels.

Three passes over the rows give the reference's mesh in the reference's order without any
sorting or atomic counter: count each row's vertices and triangles, lay the rows out one after
the other (a prefix sum of the counts), then write each row's vertices and triangles into its
own part of the output. A vertex is written by the row that owns its edge, if some kept
triangle of the up to four cubes around the edge uses it (edge_used), so vertices come sorted
by edge id as in the reference; a triangle's corners find their vertex index by a binary search
among the vertices of the row that owns their edge.

The case table and the edge offsets are the reference's arrays, captured as constants.
"""

from __future__ import annotations

from collections.abc import Callable
from types import SimpleNamespace
from typing import Any

import numpy as np

from kintinuous_ref.marching_cubes import (
    EDGE_OFFSETS,
    EDGES,
    SHARE_TOLERANCE,
    TRIANGLE_COUNTS,
    TRIANGLES,
)


def _local_edges() -> np.ndarray:
    """(3, 8) the cube edge along `axis` whose lower corner is c (-1 where c has bit `axis`)."""
    table = np.full((3, 8), -1, dtype=np.int64)
    for e, (lower, _, axis) in enumerate(EDGES):
        table[axis, lower] = e
    return table


def build_ops(jit: Callable[[Any], Any]) -> SimpleNamespace:
    """The per-cube and per-row functions compiled with `jit`, in one namespace."""
    cube = _build_cube(jit)
    rows = _build_rows(jit, cube)
    return SimpleNamespace(**vars(cube), **vars(rows))


def _build_cube(jit: Callable[[Any], Any]) -> SimpleNamespace:
    """One cube's case, one edge's crossing, and which of a cube's triangles are kept."""
    table, counts, offsets = TRIANGLES.astype(np.int8), TRIANGLE_COUNTS, EDGE_OFFSETS
    local_edges = _local_edges()

    @jit
    def corner_bits(tsdf: Any, i: int, j: int, k: int) -> int:
        """Bits dx + 2 dy of the voxels (i + dx, j + dy, k) that are inside (TSDF < 0)."""
        bits = 1 if tsdf[i, j, k] < 0 else 0
        bits |= 2 if tsdf[i + 1, j, k] < 0 else 0
        bits |= 4 if tsdf[i, j + 1, k] < 0 else 0
        return bits | (8 if tsdf[i + 1, j + 1, k] < 0 else 0)

    @jit
    def edge_crossing(tsdf: Any, weight: Any, min_weight: float, edge: tuple) -> tuple:
        """(t, kept) of the edge `edge` = (i, j, k, axis): its zero crossing t = f0 / (f0 - f1)
        and whether the reference keeps its vertex (voxels with a share >= SHARE_TOLERANCE
        observed). Only for crossed edges, where f0 != f1."""
        i, j, k, axis = edge
        i1, j1, k1 = i + (axis == 0), j + (axis == 1), k + (axis == 2)
        f0, f1 = np.float64(tsdf[i, j, k]), np.float64(tsdf[i1, j1, k1])
        t = f0 / (f0 - f1)
        lower_ok = np.float64(weight[i, j, k]) > min_weight or 1.0 - t < SHARE_TOLERANCE
        upper_ok = np.float64(weight[i1, j1, k1]) > min_weight or t < SHARE_TOLERANCE
        return t, lower_ok and upper_ok

    @jit
    def cube_edge(cube: tuple, edge: int) -> tuple:
        """Cube edge `edge` of the cube with lower voxel `cube` as (i, j, k, axis)."""
        i, j, k = cube
        return (i + offsets[edge, 0], j + offsets[edge, 1], k + offsets[edge, 2], offsets[edge, 3])

    @jit
    def triangle_kept(
        tsdf: Any, weight: Any, min_weight: float, cube: tuple, case: int, row: int
    ) -> bool:
        """Whether triangle `row` of the cube's case has its three vertices kept."""
        for corner in range(3):
            edge = cube_edge(cube, table[case, row, corner])
            if not edge_crossing(tsdf, weight, min_weight, edge)[1]:
                return False
        return True

    @jit
    def uses_edge(tsdf: Any, weight: Any, min_weight: float, cube: tuple, edge: int) -> bool:
        """Whether a kept triangle of the cube uses its cube edge `edge`."""
        i, j, k = cube
        case = corner_bits(tsdf, i, j, k) | corner_bits(tsdf, i, j, k + 1) << 4
        for row in range(counts[case]):
            if (
                edge == table[case, row, 0]
                or edge == table[case, row, 1]
                or edge == table[case, row, 2]
            ):
                if triangle_kept(tsdf, weight, min_weight, cube, case, row):
                    return True
        return False

    @jit
    def edge_used(tsdf: Any, weight: Any, min_weight: float, edge: tuple) -> bool:
        """Whether some kept triangle of the up to four cubes around `edge` uses its vertex."""
        i, j, k, axis = edge
        last = (tsdf.shape[0] - 2, tsdf.shape[1] - 2, tsdf.shape[2] - 2)
        for corner in range(8):
            if corner >> axis & 1:
                continue
            ci, cj, ck = i - (corner & 1), j - (corner >> 1 & 1), k - (corner >> 2 & 1)
            if min(ci, cj, ck) < 0 or ci > last[0] or cj > last[1] or ck > last[2]:
                continue
            if uses_edge(tsdf, weight, min_weight, (ci, cj, ck), local_edges[axis, corner]):
                return True
        return False

    return SimpleNamespace(
        corner_bits=corner_bits,
        cube_edge=cube_edge,
        edge_crossing=edge_crossing,
        edge_used=edge_used,
        table=table,
        counts=counts,
        triangle_kept=triangle_kept,
    )


def _build_rows(jit: Callable[[Any], Any], cube: SimpleNamespace) -> SimpleNamespace:
    """A row's counts, its vertices and its triangles."""
    corner_bits, cube_edge, edge_crossing = cube.corner_bits, cube.cube_edge, cube.edge_crossing
    edge_used, triangle_kept, table, counts = (
        cube.edge_used,
        cube.triangle_kept,
        cube.table,
        cube.counts,
    )

    @jit
    def vertex_on(tsdf: Any, weight: Any, min_weight: float, edge: tuple) -> bool:
        """Whether the edge (i, j, k, axis) exists, is crossed and its vertex is used."""
        i, j, k, axis = edge
        i1, j1, k1 = i + (axis == 0), j + (axis == 1), k + (axis == 2)
        if i1 >= tsdf.shape[0] or j1 >= tsdf.shape[1] or k1 >= tsdf.shape[2]:
            return False
        if (tsdf[i, j, k] < 0) == (tsdf[i1, j1, k1] < 0):
            return False
        return edge_used(tsdf, weight, min_weight, edge)

    @jit
    def row_is_uniform(tsdf: Any, i: int, j: int) -> bool:
        """Whether the voxels (i..i+1, j..j+1, all k) are all inside or all outside: then row
        (i, j) has no vertex and no triangle. One pass without early exit, which vectorises;
        most rows of a volume are free or unseen space and end here."""
        if i > tsdf.shape[0] - 2 or j > tsdf.shape[1] - 2:
            return False
        some, every = 0, 15
        for k in range(tsdf.shape[2]):
            bits = corner_bits(tsdf, i, j, k)
            some |= bits
            every &= bits
        return some == 0 or every == 15

    @jit
    def row_vertices(tsdf: Any, weight: Any, min_weight: float, i: int, j: int) -> int:
        """How many vertices row (i, j) owns."""
        found = 0
        for k in range(tsdf.shape[2]):
            for axis in range(3):
                found += vertex_on(tsdf, weight, min_weight, (i, j, k, axis))
        return found

    @jit
    def row_triangles(tsdf: Any, weight: Any, min_weight: float, i: int, j: int) -> int:
        """How many kept triangles the cubes of row (i, j) give (none past the last cube)."""
        if i > tsdf.shape[0] - 2 or j > tsdf.shape[1] - 2:
            return 0
        found = 0
        below = corner_bits(tsdf, i, j, 0)
        for k in range(tsdf.shape[2] - 1):
            above = corner_bits(tsdf, i, j, k + 1)
            case = below | above << 4
            below = above
            for row in range(counts[case]):
                found += triangle_kept(tsdf, weight, min_weight, (i, j, k), case, row)
        return found

    @jit
    def write_row_vertices(
        tsdf: Any, weight: Any, min_weight: float, i: int, j: int, start: int, out: tuple
    ) -> None:
        """Row (i, j)'s vertices (voxel coordinates) and edge ids from index `start` on, into
        `out` = (vertices (V, 3) float64, ids (V,) int64)."""
        vertices, ids = out
        at = start
        for k in range(tsdf.shape[2]):
            for axis in range(3):
                edge = (i, j, k, axis)
                if not vertex_on(tsdf, weight, min_weight, edge):
                    continue
                t = edge_crossing(tsdf, weight, min_weight, edge)[0]
                vertices[at, 0], vertices[at, 1], vertices[at, 2] = float(i), float(j), float(k)
                vertices[at, axis] += t
                ids[at] = edge_id(tsdf.shape, edge)
                at += 1

    @jit
    def edge_id(shape: Any, edge: tuple) -> int:
        """The reference's edge id ((i ny + j) nz + k) 3 + axis."""
        i, j, k, axis = edge
        return ((i * shape[1] + j) * shape[2] + k) * 3 + axis

    @jit
    def vertex_index(shape: Any, edge: tuple, ids: Any, row_starts: Any) -> int:
        """The index of the vertex on `edge`: a binary search among its row's vertices."""
        wanted = edge_id(shape, edge)
        row = edge[0] * shape[1] + edge[1]
        lo, hi = row_starts[row], row_starts[row + 1]
        while hi - lo > 1:
            middle = (lo + hi) // 2
            if ids[middle] <= wanted:
                lo = middle
            else:
                hi = middle
        return lo

    @jit
    def write_row_triangles(
        tsdf: Any, weight: Any, min_weight: float, i: int, j: int, start: int, found: tuple
    ) -> None:
        """Row (i, j)'s kept triangles from index `start` on into `found` = (triangles (T, 3)
        int64, the vertices' ids, the rows' vertex starts (rows + 1,))."""
        triangles, ids, row_starts = found
        if i > tsdf.shape[0] - 2 or j > tsdf.shape[1] - 2:
            return
        at = start
        below = corner_bits(tsdf, i, j, 0)
        for k in range(tsdf.shape[2] - 1):
            above = corner_bits(tsdf, i, j, k + 1)
            case = below | above << 4
            below = above
            for row in range(counts[case]):
                if not triangle_kept(tsdf, weight, min_weight, (i, j, k), case, row):
                    continue
                for corner in range(3):
                    edge = cube_edge((i, j, k), table[case, row, corner])
                    triangles[at, corner] = vertex_index(tsdf.shape, edge, ids, row_starts)
                at += 1

    return SimpleNamespace(
        edge_id=edge_id,
        row_is_uniform=row_is_uniform,
        row_triangles=row_triangles,
        row_vertices=row_vertices,
        vertex_index=vertex_index,
        write_row_triangles=write_row_triangles,
        write_row_vertices=write_row_vertices,
    )
