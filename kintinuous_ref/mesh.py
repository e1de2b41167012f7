"""Surface extraction, PLY output, preview pictures, and scoring a mesh against the truth.

The triangle mesh is the TSDF's zero level set by our own marching cubes (marching_cubes.py:
Lorensen and Cline's cases, vertices welded along grid edges), so a machine without VTK still
makes meshes; pyvista and VTK only render previews and score meshes, imported where they do.
Only observed space yields surface: a vertex is kept when the voxels of its edge that its
position interpolates from have weight > min_weight (marching cubes would otherwise draw
surfaces against the 0 of never-seen voxels). Vertex colours are the colour volume's trilinear
interpolation at the vertex (paper VI-A).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from kintinuous_ref.colour import surface_colour
from kintinuous_ref.marching_cubes import marching_cubes
from kintinuous_ref.tsdf import TsdfVolume

if TYPE_CHECKING:
    import pyvista

    from kintinuous_ref.camera import Intrinsics


@dataclass
class Mesh:
    points: np.ndarray  # (V, 3) float32 world
    triangles: np.ndarray  # (T, 3) int64 vertex indices
    colours: np.ndarray  # (V, 3) uint8 RGB

    def to_pyvista(self) -> pyvista.PolyData:
        import pyvista

        cells = np.column_stack([np.full(len(self.triangles), 3), self.triangles]).ravel()
        mesh = pyvista.PolyData(self.points.astype(np.float32), cells if len(cells) else None)
        mesh.point_data["rgb"] = self.colours
        return mesh


# A marching cubes: (tsdf, weight, min_weight) -> (vertices in voxel coordinates, triangles),
# kintinuous_ref.marching_cubes's or a backend's (kintinuous_fast.mesh).
Contour = Callable[[np.ndarray, np.ndarray, float], tuple[np.ndarray, np.ndarray]]


def extract_mesh(
    volume: TsdfVolume | None, min_weight: float = 0.0, contour: Contour = marching_cubes
) -> Mesh:
    """The zero level set of the TSDF as a coloured triangle mesh (world frame), by `contour`
    on the volume's logical voxels (the cyclical buffer unrolled)."""
    empty = Mesh(
        np.zeros((0, 3), np.float32), np.zeros((0, 3), np.int64), np.zeros((0, 3), np.uint8)
    )
    if volume is None or not (volume.weight > min_weight).any():
        return empty
    tsdf, weight = volume.logical(volume.tsdf), volume.logical(volume.weight)
    vertices, triangles = contour(tsdf, weight, min_weight)
    if len(triangles) == 0:
        return empty
    points = volume.voxel_to_world(vertices)
    return Mesh(
        points=points.astype(np.float32),
        triangles=triangles,
        colours=surface_colour(volume, points),
    )


def write_ply(path: Path, mesh: Mesh) -> None:
    """Binary little-endian PLY: float x y z and uchar red green blue per vertex, triangles."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    vertex = np.zeros(
        len(mesh.points),
        dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("r", "u1"), ("g", "u1"), ("b", "u1")],
    )
    for i, axis in enumerate("xyz"):
        vertex[axis] = mesh.points[:, i]
    for i, channel in enumerate("rgb"):
        vertex[channel] = mesh.colours[:, i]
    face = np.zeros(len(mesh.triangles), dtype=[("n", "u1"), ("v", "<i4", (3,))])
    face["n"] = 3
    face["v"] = mesh.triangles
    header = (
        "ply\nformat binary_little_endian 1.0\ncomment kintinuous reconstruction\n"
        f"element vertex {len(vertex)}\n"
        "property float x\nproperty float y\nproperty float z\n"
        "property uchar red\nproperty uchar green\nproperty uchar blue\n"
        f"element face {len(face)}\nproperty list uchar int vertex_indices\nend_header\n"
    )
    with open(path, "wb") as out:
        out.write(header.encode("ascii"))
        out.write(vertex.tobytes())
        out.write(face.tobytes())


def render_preview(
    mesh: Mesh,
    path: Path,
    view_pose: np.ndarray | None = None,
    size: tuple[int, int] = (960, 720),
) -> str:
    """An off-screen picture of the coloured mesh (VTK through EGL or OSMesa, no display needed);
    '' when VTK drew it. Where VTK cannot draw (not installed, or no EGL, OSMesa or GL context)
    the picture is matplotlib's plan view (`render_plan_view`) and the one line returned says so.

    With `view_pose` (camera-to-world, e.g. the first camera) the picture is taken from a little
    behind and above that camera, looking at the mesh's centre, so it resembles the first frame.
    """
    try:
        _render_with_vtk(mesh, path, view_pose, size)
        return ""
    except ImportError as err:
        reason = f"{err.name or 'VTK'} is not installed"
    except Exception as err:  # noqa: BLE001  (any VTK failure leaves the plan view)
        reason = f"VTK cannot render here ({type(err).__name__}: {err})"
    render_plan_view(mesh, path, view_pose, size)
    return f"the preview is a plan view drawn by matplotlib: {reason}"


def _render_with_vtk(
    mesh: Mesh, path: Path, view_pose: np.ndarray | None, size: tuple[int, int]
) -> None:
    import pyvista
    import vtk

    vtk.vtkLogger.SetStderrVerbosity(vtk.vtkLogger.VERBOSITY_ERROR)  # no X-server chatter
    plotter = pyvista.Plotter(off_screen=True, window_size=size)
    plotter.set_background("white")
    if len(mesh.triangles):
        plotter.add_mesh(mesh.to_pyvista(), scalars="rgb", rgb=True, lighting=False)
        if view_pose is not None:
            look_as_camera(plotter, mesh.points, view_pose, zoom=1.2)
        else:
            plotter.view_isometric()
    plotter.screenshot(str(path))
    plotter.close()


# What rendering_status runs in a child process: one triangle drawn off-screen by VTK (a process
# without a GL context may abort rather than raise, so the probe never runs in the caller's).
_RENDER_PROBE = """
import sys, tempfile
import numpy as np
from kintinuous_ref.mesh import Mesh, _render_with_vtk
triangle = Mesh(np.eye(3, dtype=np.float32), np.array([[0, 1, 2]]), np.zeros((3, 3), np.uint8))
with tempfile.TemporaryDirectory() as folder:
    _render_with_vtk(triangle, folder + "/probe.png", None, (64, 48))
"""


def rendering_status(timeout: float = 120.0) -> str:
    """'' when VTK renders off-screen here, else why not in one line (previews are then
    matplotlib's plan views): a child process draws one triangle."""
    import subprocess
    import sys

    try:
        done = subprocess.run(
            [sys.executable, "-c", _RENDER_PROBE], capture_output=True, text=True, timeout=timeout
        )
    except subprocess.TimeoutExpired:
        return f"drawing one triangle with VTK took over {timeout:g} s"
    if done.returncode == 0:
        return ""
    lines = [line for line in done.stderr.strip().splitlines() if line.strip()]
    return lines[-1] if lines else f"drawing a triangle with VTK ended with {done.returncode}"


# The plan view draws at most this many vertices (a random subset beyond): enough to fill a
# 960 x 720 picture, few enough to draw in a second.
PLAN_VIEW_POINTS = 300_000


def render_plan_view(
    mesh: Mesh,
    path: Path,
    view_pose: np.ndarray | None = None,
    size: tuple[int, int] = (960, 720),
) -> None:
    """The mesh's vertices seen from above, in their colours, drawn by matplotlib (no GL needed).
    "Above" is against the y axis of `view_pose`'s camera (down in its image), with its x to the
    right and its viewing direction up the picture; without a pose, the world's x and y. The
    highest vertices are drawn last, so they cover what lies below them."""
    import matplotlib

    matplotlib.use("Agg")
    from matplotlib import pyplot

    points, colours = mesh.points.astype(np.float64), mesh.colours
    if len(points) > PLAN_VIEW_POINTS:
        chosen = np.random.default_rng(0).choice(len(points), PLAN_VIEW_POINTS, replace=False)
        points, colours = points[chosen], colours[chosen]
    if view_pose is not None:
        local = (points - view_pose[:3, 3]) @ view_pose[:3, :3]  # the camera's frame
        across, along, height = local[:, 0], local[:, 2], -local[:, 1]
    else:
        across, along, height = points[:, 0], points[:, 1], points[:, 2]
    order = np.argsort(height)
    dpi = 100
    figure = pyplot.figure(figsize=(size[0] / dpi, size[1] / dpi), dpi=dpi)
    axes = figure.add_axes((0, 0, 1, 1))
    axes.scatter(across[order], along[order], c=colours[order] / 255.0, s=1, marker="s", lw=0)
    axes.set_aspect("equal")
    axes.set_axis_off()
    figure.savefig(path, dpi=dpi, facecolor="white")
    pyplot.close(figure)


def look_as_camera(
    plotter: pyvista.Plotter, points: np.ndarray, view_pose: np.ndarray, zoom: float
) -> None:
    """Point `plotter` at the centre of `points` along the camera `view_pose`'s direction
    (camera-to-world), from a little above it, backed off until all of them fit, then zoomed in
    by `zoom`: a picture that resembles that camera's view."""
    centre = points.mean(axis=0)
    direction = view_pose[:3, 2] + 0.3 * view_pose[:3, 1]
    plotter.camera_position = [tuple(centre - direction), tuple(centre), tuple(-view_pose[:3, 1])]
    plotter.reset_camera()
    plotter.camera.zoom(zoom)


# ----------------------------------------------------------------------------------------------
# Scoring against a ground-truth surface


def sample_surface(truth: pyvista.PolyData, spacing: float, seed: int = 0) -> np.ndarray:
    """Points spread uniformly over a triangle mesh, about one per spacing^2 of area."""
    triangles = truth.triangulate().faces.reshape(-1, 4)[:, 1:]
    corners = np.asarray(truth.points, dtype=np.float64)[triangles]  # (T, 3, 3)
    areas = 0.5 * np.linalg.norm(
        np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]), axis=1
    )
    rng = np.random.default_rng(seed)
    count = int(np.ceil(areas.sum() / spacing**2))
    chosen = rng.choice(len(areas), size=count, p=areas / areas.sum())
    a, b = rng.random(count), rng.random(count)
    flip = a + b > 1  # fold the unit square onto the triangle
    a[flip], b[flip] = 1 - a[flip], 1 - b[flip]
    c = corners[chosen]
    return c[:, 0] + a[:, None] * (c[:, 1] - c[:, 0]) + b[:, None] * (c[:, 2] - c[:, 0])


def visible_from(
    points: np.ndarray,
    depths: list[np.ndarray],
    poses: list[np.ndarray],
    camera: Intrinsics,
    tolerance: float = 0.02,
) -> np.ndarray:
    """True for points that some camera saw: they project into its depth map where the
    measured depth is within `tolerance` of their own (not occluded, not missing)."""
    seen = np.zeros(len(points), dtype=bool)
    for depth, pose in zip(depths, poses, strict=True):
        local = (points - pose[:3, 3]) @ pose[:3, :3]
        z = local[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            u = np.rint(camera.fx * local[:, 0] / z + camera.cx)
            v = np.rint(camera.fy * local[:, 1] / z + camera.cy)
        inside = (z > 0) & (u >= 0) & (u < camera.width) & (v >= 0) & (v < camera.height)
        measured = np.zeros(len(points))
        measured[inside] = depth[v[inside].astype(int), u[inside].astype(int)]
        seen |= inside & (measured > 0) & (np.abs(measured - z) < tolerance)
    return seen


def closest_on(
    surface: pyvista.PolyData, points: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(distance, closest point, cell index) from each point to a triangle mesh (exact)."""
    if len(points) == 0:
        return np.zeros(0), np.zeros((0, 3)), np.zeros(0, dtype=int)
    cells, closest = surface.find_closest_cell(points, return_closest_point=True)
    return np.linalg.norm(points - closest, axis=1), closest, cells


def _colour_at(truth: pyvista.PolyData, closest: np.ndarray, cells: np.ndarray) -> np.ndarray:
    """Barycentric interpolation of the truth's vertex colours ("rgb") at points on its cells."""
    triangles = truth.faces.reshape(-1, 4)[:, 1:][cells]
    corners = np.asarray(truth.points, dtype=np.float64)[triangles]
    e1, e2 = corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]
    d = closest - corners[:, 0]
    d11, d12, d22 = (e1 * e1).sum(1), (e1 * e2).sum(1), (e2 * e2).sum(1)
    d1, d2 = (d * e1).sum(1), (d * e2).sum(1)
    det = d11 * d22 - d12 * d12
    b1 = (d22 * d1 - d12 * d2) / det
    b2 = (d11 * d2 - d12 * d1) / det
    rgb = np.asarray(truth.point_data["rgb"], dtype=np.float64)[triangles]
    return (1 - b1 - b2)[:, None] * rgb[:, 0] + b1[:, None] * rgb[:, 1] + b2[:, None] * rgb[:, 2]


# A vertex whose colour is off by more than this (mean over RGB, 0..255) shows a foreign colour
# (bleed from another surface), not just blurred texture.
BLEED_LEVELS = 50.0


@dataclass
class SurfaceScore:
    accuracy: float  # mean distance from reconstructed vertices to the true surface, metres
    accuracy_median: float
    completeness: float  # share of visible true surface within `completeness_radius` of the mesh
    completeness_radius: float
    colour_error: float  # mean absolute RGB difference (0..255) of coloured vertices vs the truth
    colour_bleed: float  # share of coloured vertices whose error exceeds BLEED_LEVELS
    uncoloured: float  # share of vertices that received no colour
    vertices: int
    visible_samples: int

    def as_dict(self) -> dict:
        return dict(vars(self))


def surface_accuracy(
    mesh: Mesh,
    truth: pyvista.PolyData,
    visible_samples: np.ndarray,
    completeness_radius: float = 0.01,
) -> SurfaceScore:
    """Score a reconstruction against the true surface (with its "rgb" vertex colours).

    accuracy: mean distance from each reconstructed vertex to the true surface;
    completeness: share of `visible_samples` (true-surface points some camera saw, see
    sample_surface and visible_from) lying within `completeness_radius` of the mesh;
    colour error: mean absolute per-channel difference between each coloured vertex and the true
    colour at its closest true-surface point; colour bleed: the share of coloured vertices off by
    more than BLEED_LEVELS.
    """
    distance, closest, cells = closest_on(truth, mesh.points.astype(np.float64))
    coloured = mesh.colours.astype(int).sum(axis=1) > 0
    if coloured.any():
        true_colour = _colour_at(truth, closest[coloured], cells[coloured])
        per_vertex = np.abs(mesh.colours[coloured] - true_colour).mean(axis=1)
        colour_error = float(per_vertex.mean())
        colour_bleed = float((per_vertex > BLEED_LEVELS).mean())
    else:
        colour_error = colour_bleed = float("nan")
    if len(mesh.triangles) and len(visible_samples):
        to_mesh, _, _ = closest_on(mesh.to_pyvista(), visible_samples)
        completeness = float((to_mesh <= completeness_radius).mean())
    else:
        completeness = 0.0
    return SurfaceScore(
        accuracy=float(distance.mean()) if len(distance) else float("nan"),
        accuracy_median=float(np.median(distance)) if len(distance) else float("nan"),
        completeness=completeness,
        completeness_radius=completeness_radius,
        colour_error=colour_error,
        colour_bleed=colour_bleed,
        uncoloured=float(1.0 - coloured.mean()) if len(coloured) else 0.0,
        vertices=len(mesh.points),
        visible_samples=len(visible_samples),
    )
