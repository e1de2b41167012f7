"""The surface in a box of a cyclical volume, by the moving volume's rules (moving_volume.py): what
each backend's mesh stage computes for a slice (`mesh_box`: kintinuous_ref.marching_cubes's with
its marching cubes, the cpu backend's with its own, the cuda backend's on the device, where its
volume lies), the moving volume then naming each vertex by its global grid edge.

The box. The logical voxels [lo, hi) of a volume whose logical voxel l is stored in array cell
(l + offset) mod N (tsdf.TsdfVolume.cells: the box may wrap around the buffer). Marching cubes
runs on the box alone, in its own index units: a vertex's coordinates stay small and exact
enough to name the grid edge it lies on (world coordinates could be kilometres), and every cube
with all 8 voxels in the box is triangulated once.

The edge of a vertex. Two of its coordinates are whole numbers and the third is not, so it lies
on the grid edge along that axis from voxel floor(x) to floor(x) + 1; where no coordinate is
farther than ON_EDGE from a whole number, it sits on a voxel (axis ON_VOXEL, both ends that
voxel).

Observed voxels only. The contour keeps a vertex where the voxels it interpolates from have
weight >= min_weight (marching_cubes.py's rule, with the float below min_weight as its bound).
The slices are stricter: a vertex is kept only where BOTH voxels of its edge reach min_weight,
whatever share each has in its position, so that a slice holds no surface next to voxels seen
fewer than min_weight times (docs/parameters.md). A triangle is kept when its three vertices
are; vertices that no kept triangle uses are dropped, the rest keep their order.

Colour. A vertex's RGB is the linear interpolation along its edge of the edge's voxels that
received colour (colour.surface_colour restricted to an edge), black where neither did.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

# Voxels: a vertex coordinate closer than this to a whole number lies on it.
ON_EDGE = 1e-3
# The axis of a vertex that sits on a voxel (the slices' key code, slices.ON_VOXEL).
ON_VOXEL = 3

# A marching cubes: (tsdf, weight, min_weight) -> (vertices (V, 3), triangles (T, 3)), a
# vertex kept where the voxels it interpolates from have weight > min_weight.
Contour = Callable[[np.ndarray, np.ndarray, float], tuple[np.ndarray, np.ndarray]]


@dataclass
class BoxSurface:
    """The kept surface of a box: vertices in the box's voxel coordinates (V, 3) float64,
    triangles (T, 3) int64, colours (V, 3) uint8, and each vertex's grid edge (V, 4) int64:
    its lower voxel in the box and its axis (ON_VOXEL on a voxel)."""

    vertices: np.ndarray
    triangles: np.ndarray
    colours: np.ndarray
    edges: np.ndarray


def no_surface() -> BoxSurface:
    """A box without surface."""
    return BoxSurface(
        vertices=np.zeros((0, 3), np.float64),
        triangles=np.zeros((0, 3), np.int64),
        colours=np.zeros((0, 3), np.uint8),
        edges=np.zeros((0, 4), np.int64),
    )


def box_surface(
    volume: Any,
    lo: tuple[int, int, int],
    hi: tuple[int, int, int],
    min_weight: float,
    contour: Contour,
) -> BoxSurface:
    """The surface of the logical voxel box [lo, hi) of `volume` (a tsdf.TsdfVolume, or a view
    with its cells(), weight, tsdf, colour and colour_weight) by `contour`, a vertex kept when
    both voxels of its edge have weight >= min_weight (module docstring)."""
    cells = volume.cells(tuple(lo), tuple(hi))
    weight = volume.weight[cells]
    if min(weight.shape) < 2 or not (weight >= min_weight).any():
        return no_surface()
    # weight >= m is weight > the float below m, the contour's rule.
    below = float(np.nextafter(min_weight, -np.inf))
    local, triangles = contour(volume.tsdf[cells], weight, below)
    if len(triangles) == 0:
        return no_surface()
    axis, lower, upper = vertex_edges(local, weight.shape)

    w_lower = weight[lower[:, 0], lower[:, 1], lower[:, 2]]
    w_upper = weight[upper[:, 0], upper[:, 1], upper[:, 2]]
    keep = (w_lower >= min_weight) & (w_upper >= min_weight)
    triangles = triangles[keep[triangles].all(axis=1)]
    if len(triangles) == 0:
        return no_surface()
    used = np.zeros(len(local), dtype=bool)
    used[triangles.ravel()] = True
    local, lower, upper, axis = local[used], lower[used], upper[used], axis[used]
    return BoxSurface(
        vertices=local,
        triangles=(np.cumsum(used) - 1)[triangles],
        colours=edge_colours(volume, cells, local, (lower, upper, axis)),
        edges=np.column_stack([lower, axis]),
    )


def vertex_edges(local: np.ndarray, shape: tuple[int, ...]) -> tuple[np.ndarray, ...]:
    """(axis (V,), lower (V, 3), upper (V, 3)) of each vertex (V, 3) in a box of `shape`
    voxels: the axis of the grid edge it lies on (ON_VOXEL on a voxel: the first coordinate
    farthest from a whole number, none farther than ON_EDGE) and the edge's two voxels (the same
    voxel twice on a voxel), clipped to the box (module docstring)."""
    distance = np.abs(local - np.rint(local))
    axis = np.argmax(distance, axis=1)
    axis[distance.max(axis=1) < ON_EDGE] = ON_VOXEL
    lower = np.rint(local).astype(np.int64)
    along = np.flatnonzero(axis < 3)
    lower[along, axis[along]] = np.floor(local[along, axis[along]]).astype(np.int64)
    lower = np.clip(lower, 0, np.array(shape) - 1)
    upper = lower.copy()
    upper[along, axis[along]] += 1
    upper = np.minimum(upper, np.array(shape) - 1)
    return axis, lower, upper


def edge_colours(
    volume: Any, cells: tuple, local: np.ndarray, edges: tuple[np.ndarray, ...]
) -> np.ndarray:
    """RGB (V, 3) uint8 of vertices on grid edges, edges = (lower, upper, axis) as vertex_edges
    gives them: the linear interpolation t from the lower voxel to the upper one over those of
    the two that received colour, rounded to the nearest level; black if neither did."""
    lower, upper, axis = edges
    colours = np.zeros((len(local), 3), dtype=np.uint8)
    if volume.colour is None or len(local) == 0:
        return colours
    rgb, weight = volume.colour[cells], volume.colour_weight[cells]
    t = np.zeros(len(local))
    along = np.flatnonzero(axis < 3)
    t[along] = local[along, axis[along]] - lower[along, axis[along]]
    total = np.zeros((len(local), 3))
    coverage = np.zeros(len(local))
    for end, w in ((lower, 1.0 - t), (upper, t)):
        i, j, k = end.T
        w = w * (weight[i, j, k] > 0)
        total += w[:, None] * rgb[i, j, k]
        coverage += w
    coloured = coverage > 1e-6
    colours[coloured] = np.clip(np.rint(total[coloured] / coverage[coloured, None]), 0, 255)
    return colours
