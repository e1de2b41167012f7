"""Marching cubes (Lorensen and Cline, SIGGRAPH 1987) on the TSDF: the zero level set as a welded,
consistently oriented triangle mesh, in NumPy, with no VTK.

The cube. A cube is named by its lower voxel (i, j, k) and has 8 corners c = dx + 2 dy + 4 dz
(dx, dy, dz in {0, 1}). Its CASE index has bit c set when corner c is inside (TSDF < 0, behind
the surface): 256 cases (Lorensen-Cline's "index" into their table). A cube edge joins two
corners that differ on one axis; the surface crosses it when exactly one of them is inside.

The crossing. The TSDF is taken as linear along an edge from f0 (lower voxel) to f1 (upper):
f(t) = f0 + t (f1 - f0) = 0 at t = f0 / (f0 - f1), in [0, 1) because f0 >= 0 > f1 or
f0 < 0 <= f1 (a 0 counts as outside), so f0 - f1 is never 0 on a crossed edge.

Welding. A vertex belongs to a grid EDGE, not to a cube: the edge along `axis` from voxel
(i, j, k) has the id ((i ny + j) nz + k) 3 + axis, and its crossing is computed from its two
voxels alone, so the up to four cubes around the edge name the same vertex. The mesh is
therefore welded (one vertex per crossed edge), and vertices come sorted by edge id.

The table (TRIANGLES) is derived here rather than typed in, from the cube's faces: on each face
the crossed edges are joined in pairs by segments that cut off each run of inside corners (on a
face with two diagonal inside corners, each inside corner alone: the same choice from both
cubes that share the face, which is what keeps the mesh free of Lorensen-Cline's holes between
ambiguous neighbours). Each segment is directed so that the outside lies to the left of it seen
from outside the cube; the segments then chain into closed loops, each fanned into triangles
whose normals (right-hand rule) point towards positive TSDF, i.e. free space, as VTK's contour
does for our sign convention.

Observed space only. A voxel is observed when its weight exceeds `min_weight`. A vertex is kept
when every voxel of its edge with a share of at least SHARE_TOLERANCE in its interpolation
(1 - t for the lower voxel, t for the upper) is observed (a vertex on a voxel depends on that
voxel alone), as the trilinear rule of the mesh's former VTK path; a triangle is kept when its
three vertices are; vertices that no kept triangle uses are dropped.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from kintinuous_ref.box_surface import BoxSurface, box_surface

if TYPE_CHECKING:
    from kintinuous_ref.tsdf import TsdfVolume

# A voxel whose share of a vertex's interpolation is below this does not decide whether the
# vertex is kept.
SHARE_TOLERANCE = 1e-4
# Most triangles a case gives (the derived table's longest row).
MAX_TRIANGLES = 5


# ----------------------------------------------------------------------------------------------
# The cube's topology and the derived case table


def _corner(c: int) -> np.ndarray:
    return np.array([c & 1, (c >> 1) & 1, (c >> 2) & 1])


def _cube_edges() -> list[tuple[int, int, int]]:
    """The 12 edges as (lower corner, upper corner, axis), along x, then y, then z."""
    return [(c, c | 1 << axis, axis) for axis in range(3) for c in range(8) if not c >> axis & 1]


EDGES = _cube_edges()
# Per cube edge: the offset of its lower voxel from the cube's, and its axis.
EDGE_OFFSETS = np.array([[*_corner(a), axis] for a, _, axis in EDGES], dtype=np.int64)
_EDGE_OF = {frozenset((a, b)): e for e, (a, b, _) in enumerate(EDGES)}


def _faces() -> list[tuple[np.ndarray, list[int]]]:
    """The 6 faces as (outward normal, its 4 corners in cyclic order)."""
    faces = []
    for axis in range(3):
        u, v = (a for a in range(3) if a != axis)
        for side in (0, 1):
            cycle = [side << axis | x << u | y << v for x, y in ((0, 0), (1, 0), (1, 1), (0, 1))]
            normal = np.zeros(3)
            normal[axis] = 1.0 if side else -1.0
            faces.append((normal, cycle))
    return faces


def _face_segments(case: int, normal: np.ndarray, cycle: list[int]) -> list[tuple[int, int]]:
    """Directed segments (edge, edge) on one face: one per run of consecutive inside corners
    around the cycle, from the edge entering the run to the edge leaving it or back, whichever
    keeps the outside to the segment's left seen from outside (normal x direction points out)."""
    inside = [bool(case >> c & 1) for c in cycle]
    if all(inside) or not any(inside):
        return []
    start = next(i for i in range(4) if inside[i] and not inside[i - 1])  # a run's first corner
    segments = []
    for shift in range(4):
        i = (start + shift) % 4
        if not inside[i] or inside[i - 1]:
            continue
        run = [cycle[i]]
        while inside[(i + len(run)) % 4]:
            run.append(cycle[(i + len(run)) % 4])
        enter = _EDGE_OF[frozenset((cycle[i - 1], cycle[i]))]
        leave = _EDGE_OF[frozenset((run[-1], cycle[(i + len(run)) % 4]))]
        p, q = _midpoint(enter), _midpoint(leave)
        run_centre = np.mean([_corner(c) for c in run], axis=0)
        towards_run = run_centre - 0.5 * (p + q)
        if np.dot(np.cross(normal, q - p), towards_run) > 0:
            enter, leave = leave, enter
        segments.append((enter, leave))
    return segments


def _midpoint(edge: int) -> np.ndarray:
    a, b, _ = EDGES[edge]
    return 0.5 * (_corner(a) + _corner(b))


def _case_triangles(case: int) -> list[tuple[int, int, int]]:
    """The triangles (cube edges) of one case: the face segments chained into loops (every
    crossed edge lies on two faces, so it has one segment in and one out), each fanned."""
    following = {}
    for normal, cycle in _faces():
        following.update(_face_segments(case, normal, cycle))
    triangles = []
    while following:
        loop = [min(following)]
        while following[loop[-1]] != loop[0]:
            loop.append(following.pop(loop[-1]))
        following.pop(loop[-1])
        triangles += _triangulate(loop)
    return triangles


def _share_a_face(a: int, b: int) -> bool:
    """True when cube edges a and b lie on one face of the cube."""
    corners = {*EDGES[a][:2], *EDGES[b][:2]}
    return any(len({c >> axis & 1 for c in corners}) == 1 for axis in range(3))


def _triangulate(loop: list[int]) -> list[tuple[int, int, int]]:
    """The loop as triangles in its own orientation, with no diagonal between two edges of one
    face: such a diagonal would lie in the face, where the neighbouring cube may draw it too,
    and the mesh would have an edge with four triangles. The first such triangulation in order
    (the triangle on the closing side loop[-1] -> loop[0], its apex the earliest possible)."""
    if len(loop) < 3:
        return []
    first, last = loop[0], loop[-1]
    for k in range(1, len(loop) - 1):
        apex = loop[k]
        chords = [(first, apex)] * (k > 1) + [(apex, last)] * (k < len(loop) - 2)
        if any(_share_a_face(a, b) for a, b in chords):
            continue
        left, right = _triangulate(loop[: k + 1]), _triangulate(loop[k:])
        if (k == 1 or left) and (k == len(loop) - 2 or right):
            return [*left, (last, first, apex), *right]
    return []


def _case_table() -> tuple[np.ndarray, np.ndarray]:
    """(TRIANGLES (256, MAX_TRIANGLES, 3) int64 cube edges, -1 past each case's end,
    TRIANGLE_COUNTS (256,))."""
    table = np.full((256, MAX_TRIANGLES, 3), -1, dtype=np.int64)
    counts = np.zeros(256, dtype=np.int64)
    for case in range(256):
        triangles = _case_triangles(case)
        counts[case] = len(triangles)
        if triangles:
            table[case, : len(triangles)] = triangles
    return table, counts


TRIANGLES, TRIANGLE_COUNTS = _case_table()


# ----------------------------------------------------------------------------------------------
# The volume's mesh


def _cube_cases(tsdf: np.ndarray) -> np.ndarray:
    """The case index of every cube (shape N - 1 per axis): bit c set where corner c < 0."""
    inside = tsdf < 0
    nx, ny, nz = (s - 1 for s in tsdf.shape)
    cases = np.zeros((nx, ny, nz), dtype=np.int64)
    for c in range(8):
        dx, dy, dz = _corner(c)
        cases |= inside[dx : dx + nx, dy : dy + ny, dz : dz + nz].astype(np.int64) << c
    return cases


def _edge_ids(shape: tuple[int, ...], voxels: np.ndarray, axis: np.ndarray) -> np.ndarray:
    """The id of the edge along `axis` from each voxel (M, 3) of a volume of `shape`."""
    return ((voxels[:, 0] * shape[1] + voxels[:, 1]) * shape[2] + voxels[:, 2]) * 3 + axis


def _edge_crossings(
    tsdf: np.ndarray, weight: np.ndarray, min_weight: float, ids: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """(position in voxel coordinates (M, 3), kept (M,)) of the vertices on edges `ids`."""
    axis = ids % 3
    lower = np.column_stack(np.unravel_index(ids // 3, tsdf.shape))
    upper = lower + np.eye(3, dtype=np.int64)[axis]
    f0 = tsdf[tuple(lower.T)].astype(np.float64)
    f1 = tsdf[tuple(upper.T)].astype(np.float64)
    t = f0 / (f0 - f1)
    positions = lower.astype(np.float64)
    positions[np.arange(len(ids)), axis] += t
    lower_observed = weight[tuple(lower.T)].astype(np.float64) > min_weight
    upper_observed = weight[tuple(upper.T)].astype(np.float64) > min_weight
    kept = (lower_observed | (1.0 - t < SHARE_TOLERANCE)) & (upper_observed | (t < SHARE_TOLERANCE))
    return positions, kept


def marching_cubes(
    tsdf: np.ndarray, weight: np.ndarray, min_weight: float
) -> tuple[np.ndarray, np.ndarray]:
    """The zero level set of `tsdf` (a 3-d array) over voxels with weight > `min_weight`
    (module docstring): (vertices (V, 3) float64 in voxel coordinates, sorted by edge id,
    triangles (T, 3) int64, cube by cube in C order and each case's table order)."""
    empty = np.zeros((0, 3), dtype=np.float64), np.zeros((0, 3), dtype=np.int64)
    if min(tsdf.shape) < 2:
        return empty
    cases = _cube_cases(tsdf)
    cubes = np.column_stack(np.nonzero(TRIANGLE_COUNTS[cases] > 0))
    if len(cubes) == 0:
        return empty
    rows = TRIANGLES[cases[tuple(cubes.T)]]  # (C, MAX_TRIANGLES, 3) cube edges
    valid = rows[..., 0] >= 0
    cube_of = np.broadcast_to(cubes[:, None, None, :], (*rows.shape, 3))[valid]
    local = rows[valid]  # (T, 3)
    offsets = EDGE_OFFSETS[local]  # (T, 3, 4)
    voxels = cube_of + offsets[..., :3]
    ids = _edge_ids(tsdf.shape, voxels.reshape(-1, 3), offsets[..., 3].reshape(-1))
    ids = ids.reshape(-1, 3)
    unique, corners = np.unique(ids, return_inverse=True)
    positions, kept = _edge_crossings(tsdf, weight, min_weight, unique)
    ids = ids[kept[corners.reshape(-1, 3)].all(axis=1)]
    if len(ids) == 0:
        return empty
    unique, corners = np.unique(ids, return_inverse=True)
    positions, _ = _edge_crossings(tsdf, weight, min_weight, unique)
    return positions, corners.reshape(-1, 3).astype(np.int64)


def mesh_box(
    volume: TsdfVolume, lo: tuple[int, int, int], hi: tuple[int, int, int], min_weight: float
) -> BoxSurface:
    """The surface of the logical voxel box [lo, hi) of `volume` (it may wrap around the
    cyclical buffer) by this marching cubes and the moving volume's slice rules
    (box_surface.py): a vertex kept where both voxels of its edge have weight >= min_weight,
    with its colour and grid edge. Each backend's mesh stage has one, computed where its
    volume lies (the cuda backend's on the device, downloading the surface only)."""
    return box_surface(volume, lo, hi, min_weight, marching_cubes)
