"""The moving volume's slice rules (kintinuous_ref.box_surface) as per-element device functions,
for the cuda target, whose slices are meshed where the volume lies: a box of the cyclical volume
read into the marching cubes' arrays, each vertex's grid edge, the edge rule and the vertex's
colour. The cpu backend runs the reference's NumPy for them around its marching cubes (per
vertex, a small cost beside the marching cubes over the box).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from types import SimpleNamespace
from typing import Any

import numpy as np

from kintinuous_fast.targets import build_rint
from kintinuous_fast.tsdf.voxel import TSDF_SCALE
from kintinuous_ref.box_surface import ON_EDGE, ON_VOXEL


def build_slice_ops(jit: Callable[[Any], Any]) -> SimpleNamespace:
    """A slice's per-voxel and per-vertex functions compiled with `jit`, each in the reference's
    arithmetic (tsdf/volume.py's SlabView dequantisation; kintinuous_ref.box_surface's
    vertex_edges, edge rule and edge_colours), so that the surface is the one the reference's
    rules give for the same fast volume, bit for bit."""
    rint = build_rint(jit)[0]
    scale = np.float32(TSDF_SCALE)

    @jit
    def cell(index: int, offset: int, n: int) -> int:
        """Array cell of logical index `index` in [0, N) with buffer offset in [0, N)."""
        c = index + offset
        return c - n if c >= n else c

    @jit
    def read_box_voxel(packed: Any, box: tuple, voxel: tuple, out: tuple) -> None:
        """Voxel (i, j, k) of the logical box whose first voxel is `box` = (lo (3), offsets
        (3), N) into `out` = (tsdf, weight) float32 arrays of the box's shape: the TSDF
        dequantised as int16 / 32767 in float32, the weight as a float32."""
        lo, offsets, n = box
        i, j, k = voxel
        ci = cell(lo[0] + i, offsets[0], n)
        cj = cell(lo[1] + j, offsets[1], n)
        ck = cell(lo[2] + k, offsets[2], n)
        tsdf, weight = out
        tsdf[i, j, k] = np.float32(packed[ci, cj, ck, 0]) / scale
        weight[i, j, k] = np.float32(packed[ci, cj, ck, 1])

    @jit
    def edge_ends(x: float, on_axis: bool, size: int) -> tuple:
        """(lower, upper) along one axis of a vertex's edge voxels, for the vertex's coordinate
        x on that axis, in a box of `size` voxels: floor(x) and floor(x) + 1 on the edge's
        axis, the nearest whole number twice on the others, clipped to the box."""
        # int(): on the GPU math.floor returns a float, which cannot index an array
        lower = int(math.floor(x)) if on_axis else int(rint(x))
        lower = min(max(lower, 0), size - 1)
        return lower, min(lower + (1 if on_axis else 0), size - 1)

    @jit
    def vertex_edge(vertices: Any, v: int, shape: Any) -> tuple:
        """(axis, lower i, j, k, upper i, j, k, t) of vertex v of (V, 3) box coordinates in a
        box of `shape` voxels (box_surface.vertex_edges): its edge's axis (ON_VOXEL on a
        voxel), its two voxels, clipped to the box, and its position t along the edge from
        the lower voxel (0 on a voxel)."""
        axis, farthest = 0, -1.0
        for c in range(3):  # the first coordinate farthest from a whole number, as np.argmax
            x = vertices[v, c]
            distance = abs(x - rint(x))
            if distance > farthest:
                axis, farthest = c, distance
        if farthest < ON_EDGE:
            axis = ON_VOXEL
        li, ui = edge_ends(vertices[v, 0], axis == 0, shape[0])
        lj, uj = edge_ends(vertices[v, 1], axis == 1, shape[1])
        lk, uk = edge_ends(vertices[v, 2], axis == 2, shape[2])
        t = 0.0
        if axis == 0:
            t = vertices[v, 0] - float(li)
        elif axis == 1:
            t = vertices[v, 1] - float(lj)
        elif axis == 2:
            t = vertices[v, 2] - float(lk)
        return axis, li, lj, lk, ui, uj, uk, t

    @jit
    def vertex_kept(weight: Any, edge: tuple, min_weight: Any) -> bool:
        """Whether both voxels of the vertex's edge (vertex_edge) have weight >= min_weight
        (a float32, as NumPy compares a float32 array with a Python float)."""
        lower_ok = weight[edge[1], edge[2], edge[3]] >= min_weight
        return lower_ok and weight[edge[4], edge[5], edge[6]] >= min_weight

    @jit
    def end_weight(colour: Any, box: tuple, end: tuple, share: float) -> tuple:
        """(share where the voxel `end` of the box received colour, else 0; the voxel's cell)
        of one end of a vertex's edge (box_surface.edge_colours)."""
        lo, offsets, n = box
        ci = cell(lo[0] + end[0], offsets[0], n)
        cj = cell(lo[1] + end[1], offsets[1], n)
        ck = cell(lo[2] + end[2], offsets[2], n)
        return (share if colour[ci, cj, ck, 3] > 0 else 0.0), ci, cj, ck

    @jit
    def write_vertex_colour(colour: Any, box: tuple, edge: tuple, out: Any, at: int) -> None:
        """out[at] = the vertex's RGB: the linear interpolation along its edge of the edge's
        voxels that received colour (colour volume (N, N, N, 4) uint8, RGB + colour weight),
        black where neither did (box_surface.edge_colours)."""
        t = edge[7]
        wl, li, lj, lk = end_weight(colour, box, (edge[1], edge[2], edge[3]), 1.0 - t)
        wu, ui, uj, uk = end_weight(colour, box, (edge[4], edge[5], edge[6]), t)
        coverage = wl + wu
        for c in range(3):
            value = 0.0
            if coverage > 1e-6:
                total = wl * float(colour[li, lj, lk, c])
                total += wu * float(colour[ui, uj, uk, c])
                value = min(max(rint(total / coverage), 0.0), 255.0)
            out[at, c] = np.uint8(value)

    return SimpleNamespace(
        read_box_voxel=read_box_voxel,
        vertex_edge=vertex_edge,
        vertex_kept=vertex_kept,
        write_vertex_colour=write_vertex_colour,
    )
