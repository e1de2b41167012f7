"""The reference marching cubes: every case of the derived table is a closed, consistently
oriented patch on its cube; meshes of random fields are watertight and oriented away from the
inside; a sphere's mesh is VTK's flying-edges surface; only observed voxels yield a surface."""

from collections import Counter

import numpy as np
import pytest
from scipy.spatial import cKDTree

from kintinuous_ref import marching_cubes as mc

CORNERS = np.array([[c & 1, c >> 1 & 1, c >> 2 & 1] for c in range(8)], dtype=float)
MIDPOINTS = np.array([(CORNERS[a] + CORNERS[b]) / 2 for a, b, _ in mc.EDGES])


def case_triangles(case):
    return mc.TRIANGLES[case, : mc.TRIANGLE_COUNTS[case]]


def share_a_face(a, b):
    corners = CORNERS[[*mc.EDGES[a][:2], *mc.EDGES[b][:2]]]
    return bool((corners == corners[0]).all(axis=0).any())


def crossed_edges(case):
    return {e for e, (a, b, _) in enumerate(mc.EDGES) if (case >> a & 1) != (case >> b & 1)}


def trilinear_gradient(values, point):
    gradient = np.zeros(3)
    for corner, value in zip(CORNERS, values, strict=True):
        for axis in range(3):
            w = 2 * corner[axis] - 1
            for other in set(range(3)) - {axis}:
                w *= point[other] if corner[other] else 1 - point[other]
            gradient[axis] += value * w
    return gradient


@pytest.mark.parametrize("case", range(256))
def test_every_case_is_a_closed_oriented_patch(case):
    triangles = case_triangles(case)
    assert {int(e) for e in triangles.ravel()} == crossed_edges(case)
    assert len({tuple(sorted(t)) for t in triangles}) == len(triangles)  # no duplicates
    corners = MIDPOINTS[triangles]
    normals = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    assert (np.linalg.norm(normals, axis=1) > 1e-6).all()  # no degenerate triangle
    directed = Counter((int(t[i]), int(t[(i + 1) % 3])) for t in triangles for i in range(3))
    assert max(directed.values(), default=1) == 1  # consistently oriented
    # Inside the cube every edge has its opposite; the open ones pair two crossed edges of a
    # face, and each crossed edge ends two of them (one on each of its faces): closed.
    open_edges = [edge for edge in directed if edge[::-1] not in directed]
    assert all(share_a_face(*edge) for edge in open_edges)
    ends = Counter(e for edge in open_edges for e in edge)
    assert set(ends) == crossed_edges(case) and set(ends.values()) <= {2}
    # Normals point up the trilinear field (inside -1, outside +1): towards free space.
    values = [-1.0 if case >> c & 1 else 1.0 for c in range(8)]
    for normal, centre in zip(normals, corners.mean(axis=1), strict=True):
        assert normal @ trilinear_gradient(values, centre) > 0


def edge_uses(triangles):
    return Counter((int(t[i]), int(t[(i + 1) % 3])) for t in triangles for i in range(3))


def on_border(vertices, shape):
    return (vertices <= 0) | (vertices >= np.array(shape) - 1)


@pytest.mark.parametrize("seed", range(4))
def test_random_fields_give_watertight_oriented_meshes(seed):
    field = np.random.default_rng(seed).standard_normal((13, 12, 11)).astype(np.float32)
    vertices, triangles = mc.marching_cubes(field, np.ones_like(field), 0.0)
    # welded: one vertex per crossed grid edge
    crossings = sum(int((np.diff(field < 0, axis=axis) != 0).sum()) for axis in range(3))
    assert len(vertices) == crossings
    uses = edge_uses(triangles)
    assert max(uses.values()) == 1
    border = on_border(vertices, field.shape)
    for a, b in uses:
        if (b, a) not in uses:  # an open edge lies in a face of the volume
            assert (border[a] & border[b] & (vertices[a] == vertices[b])).any()


def sphere(n=24, radius=8.3, centre=(11.4, 11.7, 11.2)):
    grid = np.indices((n, n, n)).transpose(1, 2, 3, 0) - np.array(centre)
    return (np.linalg.norm(grid, axis=-1) - radius).astype(np.float32)


def signed_volume(vertices, triangles):
    c = vertices[triangles]
    return np.einsum("ij,ij->i", c[:, 0], np.cross(c[:, 1], c[:, 2])).sum() / 6


def test_a_sphere_is_closed_and_faces_free_space():
    field = sphere()
    vertices, triangles = mc.marching_cubes(field, np.ones_like(field), 0.0)
    assert set(Counter(map(frozenset, edge_uses(triangles))).values()) == {2}
    radius = np.linalg.norm(vertices - np.array((11.4, 11.7, 11.2)), axis=1)
    np.testing.assert_allclose(radius, 8.3, atol=0.05)
    # positive: normals point out of the sphere, towards positive TSDF
    assert signed_volume(vertices, triangles) == pytest.approx(4 / 3 * np.pi * 8.3**3, rel=0.01)


def test_a_sphere_is_vtk_flying_edges_surface():
    pyvista = pytest.importorskip("pyvista")
    field = sphere()
    vertices, triangles = mc.marching_cubes(field, np.ones_like(field), 0.0)
    grid = pyvista.ImageData(dimensions=field.shape)
    grid.point_data["tsdf"] = field.ravel(order="F")
    surface = grid.contour([0.0], scalars="tsdf", method="flying_edges", compute_normals=False)
    theirs = np.asarray(surface.points, dtype=np.float64)
    assert len(vertices) == len(theirs)
    assert abs(len(triangles) - surface.n_cells) <= 0.01 * surface.n_cells
    # the same vertices, to VTK's float32 rounding
    assert cKDTree(theirs).query(vertices)[0].max() < 1e-5
    assert cKDTree(vertices).query(theirs)[0].max() < 1e-5


def test_only_observed_voxels_yield_surface():
    rng = np.random.default_rng(7)
    field = rng.standard_normal((12, 12, 12)).astype(np.float32)
    field[3, 4, 5] = 0.0  # a vertex on a voxel: only that voxel decides
    weight = np.where(rng.random(field.shape) < 0.85, 4.0, 0.0).astype(np.float32)
    weight[2:6, 2:6, 2:6] = 4.0
    weight[3, 4, 5] = 4.0
    everything, all_triangles = mc.marching_cubes(field, np.full_like(field, 9.0), 0.0)
    vertices, triangles = mc.marching_cubes(field, weight, 2.0)
    assert 0 < len(triangles) < len(all_triangles)

    def kept(point):
        base = np.floor(point).astype(int)
        t = point - base
        axis = int(np.argmax(t))
        upper = base + np.eye(3, dtype=int)[axis]
        lower_ok = weight[tuple(base)] > 2.0 or 1 - t[axis] < mc.SHARE_TOLERANCE
        return lower_ok and (weight[tuple(upper)] > 2.0 or t[axis] < mc.SHARE_TOLERANCE)

    expected = [
        tuple(map(tuple, everything[t])) for t in all_triangles if all(map(kept, everything[t]))
    ]
    assert [tuple(map(tuple, vertices[t])) for t in triangles] == expected
    assert len(np.unique(triangles)) == len(vertices)  # no vertex left unused


def test_unobserved_or_uncrossed_volumes_give_nothing():
    field = np.ones((6, 6, 6), np.float32)
    assert mc.marching_cubes(field, np.ones_like(field), 0.0)[1].shape == (0, 3)
    field[:3] = -1.0
    assert mc.marching_cubes(field, np.zeros_like(field), 0.0)[0].shape == (0, 3)
    assert mc.marching_cubes(field[:1], np.ones_like(field[:1]), 0.0)[1].shape == (0, 3)
