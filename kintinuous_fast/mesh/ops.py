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

The cuda kernels run these passes as they are. The cpu loops run the trimmed passes of
_build_trims instead (flying edges' row trims): one pass reads the whole TSDF to find each
row's crossings, and each cube in the rows' trimmed ranges is then classified once (its case
and the edges of its kept triangles), the later passes reading those entries rather than
checking the edges and cubes again.

The case table and the edge offsets are the reference's arrays, captured as constants.

The slices' rules around the marching cubes are in slice_ops.py.
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
    trims = _build_trims(jit, cube, rows)
    return SimpleNamespace(**vars(cube), **vars(rows), **vars(trims))


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


def _triangle_edges() -> np.ndarray:
    """(256, MAX_TRIANGLES) the 12-bit mask of the cube edges of each triangle of each case."""
    masks = np.zeros(TRIANGLES.shape[:2], dtype=np.int64)
    for corner in range(3):
        masks |= np.where(TRIANGLES[..., corner] >= 0, 1 << TRIANGLES[..., corner].clip(0), 0)
    return masks


def _owner_bits() -> np.ndarray:
    """(8, 4096) uint8: bit `axis` of [c, used] set where the cube edge along `axis` from the
    cube's corner c is in `used` (a 12-bit mask of cube edges): the edges that voxel, as
    corner c of the cube, owns and the cube uses."""
    table = np.zeros((8, 4096), dtype=np.uint8)
    used = np.arange(4096)
    local_edges = _local_edges()
    for corner in range(8):
        for axis in range(3):
            if local_edges[axis, corner] >= 0:
                table[corner] |= ((used >> local_edges[axis, corner] & 1) << axis).astype(np.uint8)
    return table


def _build_trims(jit: Callable[[Any], Any], cube: SimpleNamespace, rows: Any) -> SimpleNamespace:
    """The trimmed passes (flying edges' row trims, Schroeder et al. 2015): a first pass finds,
    per row of voxels, the first and last of its crossed z edges (its TRIM) and the signs of
    its two end voxels; a row of cubes then only holds surface between the trims of its four
    rows of voxels, widened to its end where their end voxels' signs differ (cube_row_range).
    Each cube in that range is classified once, as an ENTRY: its case | used << 8, where `used`
    is the 12-bit mask of the cube edges of its kept triangles (a triangle is kept when its
    three edges' vertices are, so a triangle is kept exactly when its edges are all in `used`).
    The entries are stored, one after the other row by row, and the later passes read them:
    the vertices a row of voxels owns are the edges some entry of the up to four rows of cubes
    around it uses (owned_bits), and the triangles are read off each entry."""
    corner_bits, cube_edge, edge_crossing = cube.corner_bits, cube.cube_edge, cube.edge_crossing
    table, counts = cube.table, cube.counts
    vertex_index = rows.vertex_index
    triangle_edges = _triangle_edges()
    crossed_edges = np.bitwise_or.reduce(triangle_edges, axis=1)
    owner_bits = _owner_bits()

    @jit
    def row_trim(tsdf: Any, i: int, j: int) -> tuple:
        """(first, last, signs) of the row of voxels (i, j): its first and last crossed z edge
        (nz - 1 and -1 where none), and bits 1 and 2 set where its first and last voxels are
        inside. Voxels 0..first have the first voxel's sign, last + 1..nz - 1 the last's."""
        nz = tsdf.shape[2]
        inside = np.int32(0)
        for k in range(nz):  # no early exit, 32-bit sums: vectorises; most rows end here
            inside += np.int32(tsdf[i, j, k] < 0)
        start, end = tsdf[i, j, 0] < 0, tsdf[i, j, nz - 1] < 0
        signs = (1 if start else 0) | (2 if end else 0)
        if inside == 0 or inside == nz:
            return nz - 1, -1, signs
        first = 0
        while (tsdf[i, j, first + 1] < 0) == start:
            first += 1
        last = nz - 2
        while (tsdf[i, j, last] < 0) == end:
            last -= 1
        return first, last, signs

    @jit
    def cube_row_range(trims: Any, shape: Any, i: int, j: int) -> tuple:
        """(lo, hi): the cubes (i, j, lo..hi) that can hold surface, from the trims (rows, 3) of
        the four rows of voxels (i..i+1, j..j+1); lo > hi where none."""
        if i > shape[0] - 2 or j > shape[1] - 2:
            return 0, -1
        nz, lo, hi, starts, ends = shape[2], shape[2], -1, 0, 0
        for corner in range(4):
            row = (i + (corner & 1)) * shape[1] + j + (corner >> 1)
            lo, hi = min(lo, trims[row, 0]), max(hi, trims[row, 1])
            starts |= (trims[row, 2] & 1) << corner
            ends |= (trims[row, 2] >> 1) << corner
        if starts != 0 and starts != 15:  # the ends' cubes change sign across the row
            lo = 0
        if ends != 0 and ends != 15:
            hi = nz - 2
        return lo, min(hi, nz - 2)

    @jit
    def cube_entry(tsdf: Any, weight: Any, min_weight: float, cube_: tuple, case: int) -> int:
        """The cube's case | used << 8 (used: the edges of its kept triangles)."""
        if counts[case] == 0:
            return case
        crossed = crossed_edges[case]
        i, j, k = cube_
        observed = True  # all eight voxels observed: every vertex is kept
        for corner in range(8):
            ci, cj, ck = i + (corner & 1), j + (corner >> 1 & 1), k + (corner >> 2)
            observed &= np.float64(weight[ci, cj, ck]) > min_weight
        if observed:
            return case | crossed << 8
        kept = 0
        for edge in range(12):
            if crossed >> edge & 1:
                if edge_crossing(tsdf, weight, min_weight, cube_edge(cube_, edge))[1]:
                    kept |= 1 << edge
        used = 0
        for row in range(counts[case]):
            if triangle_edges[case, row] & ~kept == 0:
                used |= triangle_edges[case, row]
        return case | used << 8

    @jit
    def entry_triangles(entry: int) -> int:
        """How many kept triangles the entry's cube gives."""
        case, used, found = entry & 255, entry >> 8, 0
        for row in range(counts[case]):
            found += triangle_edges[case, row] & ~used == 0
        return found

    @jit
    def cube_row_entries(
        tsdf: Any, weight: Any, min_weight: float, i: int, j: int, span: tuple, entries: Any
    ) -> int:
        """The entries of the cubes (i, j, lo..hi) into entries[at..], for span = (lo, hi, at);
        returns (how many kept triangles they give, the first and the last of those cubes whose
        entry uses some edge (hi + 1 and hi where none))."""
        lo, hi, at = span
        for k in range(lo, hi + 1):  # the cases first: a loop without branches, vectorised
            entries[at + k - lo] = corner_bits(tsdf, i, j, k) | corner_bits(tsdf, i, j, k + 1) << 4
        found, first, last = 0, hi + 1, hi
        for k in range(lo, hi + 1):
            case = entries[at + k - lo]
            if counts[case] != 0:
                entry = cube_entry(tsdf, weight, min_weight, (i, j, k), case)
                entries[at + k - lo] = entry
                if entry >> 8 != 0:
                    found += entry_triangles(entry)
                    first, last = min(first, k), k
        return found, first, last

    @jit
    def mark_owned(ranges: Any, entries: Any, shape: Any, i: int, j: int, found: tuple) -> int:
        """The bits of the edges row (i, j) owns into owned[at..] for found = (owners (rows, 3)
        (lo, hi, at) of each row of voxels' span of voxels that can own a vertex, owned):
        bit `axis` of owned[at + k - lo] where the edge (i, j, k, axis) has a vertex, as some
        entry of the up to four cubes around it uses it. Returns how many."""
        owners, owned = found
        row = i * shape[1] + j
        at = owners[row, 2] - owners[row, 0]
        lo, hi = used_span(ranges, shape, i, j)
        for k in range(lo, hi + 1):
            owned[at + k] = 0
        for corner in range(4):
            ci, cj = i - (corner & 1), j - (corner >> 1)
            if ci < 0 or cj < 0:
                continue
            cube_row = ci * shape[1] + cj
            entry = ranges[cube_row, 2] - ranges[cube_row, 0]
            for k in range(ranges[cube_row, 3], ranges[cube_row, 4] + 1):
                used = entries[entry + k] >> 8
                if used != 0:
                    owned[at + k] |= owner_bits[corner, used]
                    owned[at + k + 1] |= owner_bits[corner + 4, used]
        found_ = 0
        for k in range(lo, hi + 1):
            bits = owned[at + k]
            found_ += (bits & 1) + (bits >> 1 & 1) + (bits >> 2)
        return found_

    @jit
    def used_span(ranges: Any, shape: Any, i: int, j: int) -> tuple:
        """(lo, hi): the voxels (i, j, lo..hi) that can own a vertex, from the cubes with used
        edges (ranges' columns 3 and 4) of the up to four rows of cubes around the row."""
        lo, hi = shape[2], -1
        for corner in range(4):
            ci, cj = i - (corner & 1), j - (corner >> 1)
            cube_row = ci * shape[1] + cj
            if ci >= 0 and cj >= 0 and ranges[cube_row, 3] <= ranges[cube_row, 4]:
                lo, hi = min(lo, ranges[cube_row, 3]), max(hi, ranges[cube_row, 4] + 1)
        return lo, hi

    @jit
    def write_owned_vertices(
        tsdf: Any, weight: Any, min_weight: float, found: tuple, i: int, j: int, out: tuple
    ) -> None:
        """Row (i, j)'s vertices and edge ids from index `start` on into `out` = (vertices,
        ids), for found = (ranges, owners, owned, start) (mark_owned)."""
        ranges, owners, owned, start = found
        vertices, ids = out
        shape = tsdf.shape
        row = i * shape[1] + j
        first = owners[row, 2] - owners[row, 0]
        lo, hi = used_span(ranges, shape, i, j)
        at = start
        for k in range(lo, hi + 1):
            bits = owned[first + k]
            if bits == 0:
                continue
            for axis in range(3):
                if not bits >> axis & 1:
                    continue
                t = edge_crossing(tsdf, weight, min_weight, (i, j, k, axis))[0]
                vertices[at, 0], vertices[at, 1], vertices[at, 2] = float(i), float(j), float(k)
                vertices[at, axis] += t
                ids[at] = ((i * shape[1] + j) * shape[2] + k) * 3 + axis
                at += 1

    @jit
    def write_entry_triangles(
        shape: Any, span: tuple, entries: Any, i: int, j: int, found: tuple
    ) -> None:
        """The kept triangles of the cubes (i, j, lo..hi) from index `start` on into `found` =
        (triangles, the vertices' ids, the rows' vertex starts), for span = (lo, hi, the
        index of cube k's entry less k, start)."""
        lo, hi, first, start = span
        triangles, ids, row_starts = found
        at = start
        for k in range(lo, hi + 1):
            entry = entries[first + k]
            case, used = entry & 255, entry >> 8
            if used == 0:
                continue
            for row in range(counts[case]):
                if triangle_edges[case, row] & ~used != 0:
                    continue
                for corner in range(3):
                    edge = cube_edge((i, j, k), table[case, row, corner])
                    triangles[at, corner] = vertex_index(shape, edge, ids, row_starts)
                at += 1

    return SimpleNamespace(
        cube_row_entries=cube_row_entries,
        cube_row_range=cube_row_range,
        mark_owned=mark_owned,
        row_trim=row_trim,
        write_entry_triangles=write_entry_triangles,
        write_owned_vertices=write_owned_vertices,
    )
