"""Surface extraction and scoring against closed forms: a fused plane's mesh lies on the plane,
only observed space gives surface, and the scores of a shifted copy of a known surface."""

import numpy as np
import pytest
import pyvista
from mapping_scene import CAMERA

from kintinuous_ref import mesh, tsdf
from kintinuous_ref.config import VolumeConfig


@pytest.fixture(scope="module")
def fused_plane():
    volume = tsdf.make_volume(VolumeConfig(resolution=64, size=1.0), np.eye(4))
    depth = np.full((CAMERA.height, CAMERA.width), 0.6, np.float32)
    rgb = np.zeros((CAMERA.height, CAMERA.width, 3), np.uint8)
    rgb[...] = (40, 160, 90)
    tsdf.integrate(volume, depth, np.eye(4), CAMERA, rgb)
    return volume


def test_mesh_of_a_fused_plane_lies_on_it(fused_plane):
    surface = mesh.extract_mesh(fused_plane)
    assert len(surface.triangles) > 500
    # Marching cubes interpolates linearly along cell edges; on a plane's TSDF that is exact up
    # to the pixel rounding of integration (< 1 mm).
    np.testing.assert_allclose(surface.points[:, 2], 0.6, atol=1e-3)
    # Only observed space: the view spans |x| <= 0.3 m at 0.6 m (fx = 160, 160 px wide).
    assert np.abs(surface.points[:, 0]).max() < 0.3 + fused_plane.voxel_size
    coloured = surface.colours.sum(axis=1) > 0
    assert coloured.mean() > 0.9
    np.testing.assert_array_equal(surface.colours[coloured][0], [40, 160, 90])
    assert (surface.colours[coloured] == [40, 160, 90]).all()


def test_empty_volumes_give_empty_meshes():
    volume = tsdf.make_volume(VolumeConfig(resolution=16, size=1.0), np.eye(4))
    assert len(mesh.extract_mesh(volume).points) == 0
    assert len(mesh.extract_mesh(None).triangles) == 0
    volume.tsdf[...] = -1.0  # negative but never observed: still no surface
    volume.tsdf[:8] = 1.0
    assert len(mesh.extract_mesh(volume).points) == 0


def test_scores_of_a_shifted_surface():
    truth = pyvista.Plane(
        center=(0, 0, 1), direction=(0, 0, 1), i_size=1, j_size=1, i_resolution=20, j_resolution=20
    ).triangulate()
    truth.point_data["rgb"] = np.tile(np.array([100, 100, 100], np.uint8), (truth.n_points, 1))
    inner = pyvista.Plane(
        center=(0, 0, 1.005),
        direction=(0, 0, 1),
        i_size=0.5,
        j_size=0.5,
        i_resolution=10,
        j_resolution=10,
    ).triangulate()
    reconstruction = mesh.Mesh(
        np.asarray(inner.points, np.float32),
        inner.faces.reshape(-1, 4)[:, 1:],
        np.tile(np.array([110, 90, 100], np.uint8), (inner.n_points, 1)),
    )
    samples = mesh.sample_surface(truth, 0.02)
    assert abs(len(samples) - 1.0 / 0.02**2) < 2  # one per spacing^2 of the 1 m^2 plane
    np.testing.assert_allclose(samples[:, 2], 1.0)
    central = samples[np.abs(samples[:, :2]).max(axis=1) < 0.25]
    score = mesh.surface_accuracy(reconstruction, truth, central)
    assert score.accuracy == pytest.approx(0.005, abs=1e-6)  # 5 mm above the true plane
    assert score.completeness == 1.0  # every sample within 1 cm
    assert score.colour_error == pytest.approx(20 / 3, abs=1e-3)  # |+10|, |-10|, 0
    assert score.colour_bleed == 0.0  # 6.7 levels off: blur, not bleed
    tight = mesh.surface_accuracy(reconstruction, truth, central, completeness_radius=0.004)
    assert tight.completeness == 0.0
    everywhere = mesh.surface_accuracy(reconstruction, truth, samples)
    assert everywhere.completeness == pytest.approx(0.25, abs=0.03)  # a quarter of the area


def test_visibility_respects_occlusion():
    points = np.array([[0.0, 0.0, 1.0], [0.0, 0.0, 2.0], [5.0, 0.0, 1.0]])
    depth = np.full((CAMERA.height, CAMERA.width), 1.0, np.float32)  # a wall at 1 m
    seen = mesh.visible_from(points, [depth], [np.eye(4)], CAMERA)
    np.testing.assert_array_equal(seen, [True, False, False])  # on it, behind it, outside view


def test_ply_round_trip(tmp_path):
    surface = mesh.Mesh(
        np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], np.float32),
        np.array([[0, 1, 2], [0, 2, 3]]),
        np.array([[255, 0, 0], [0, 255, 0], [0, 0, 255], [9, 9, 9]], np.uint8),
    )
    mesh.write_ply(tmp_path / "m.ply", surface)
    back = pyvista.read(tmp_path / "m.ply")
    np.testing.assert_array_equal(back.points, surface.points)
    np.testing.assert_array_equal(back.faces.reshape(-1, 4)[:, 1:], surface.triangles)
    np.testing.assert_array_equal(back.point_data["RGB"], surface.colours)


def test_preview_without_vtk_is_a_plan_view_of_the_vertices(tmp_path, monkeypatch):
    """Where VTK cannot be imported the preview is matplotlib's plan view: the vertices seen from
    above the camera in their own colours, the picture of the requested size."""
    import cv2

    monkeypatch.setitem(__import__("sys").modules, "pyvista", None)  # import pyvista fails
    grid = np.stack(np.meshgrid(np.linspace(-0.5, 0.5, 60), np.linspace(1.0, 2.0, 60)), -1)
    floor = np.column_stack([grid[..., 0].ravel(), np.full(3600, 0.4), grid[..., 1].ravel()])
    colours = np.zeros((3600, 3), np.uint8)
    colours[:, 0] = 200  # a red floor 0.4 m below the camera (its y points down)
    colours[floor[:, 0] > 0, 2] = 200  # ... magenta on the camera's right
    surface = mesh.Mesh(floor.astype(np.float32), np.zeros((0, 3), np.int64), colours)
    path = tmp_path / "preview.png"
    line = mesh.render_preview(surface, path, view_pose=np.eye(4), size=(320, 240))
    assert line == "the preview is a plan view drawn by matplotlib: pyvista is not installed"
    picture = cv2.imread(str(path))[..., ::-1]  # RGB
    assert picture.shape == (240, 320, 3)
    red = (picture[..., 0] > 150) & (picture[..., 1] < 80) & (picture[..., 2] < 80)
    magenta = (picture[..., 0] > 150) & (picture[..., 1] < 80) & (picture[..., 2] > 150)
    white = picture.min(axis=2) > 240
    assert red.mean() > 0.02 and magenta.mean() > 0.02 and white.mean() > 0.3
    # the camera's right is the picture's right
    columns = np.arange(320)[None, :].repeat(240, 0)
    assert columns[magenta].mean() > columns[red].mean() + 60


def test_rendering_status_says_why_vtk_cannot_render(tmp_path, monkeypatch):
    """`kintinuous info`'s preview line: '' where VTK draws off-screen (this machine), else the
    child's last error line; here a sitecustomize makes `import pyvista` fail in the child."""
    import os

    assert mesh.rendering_status() == ""
    (tmp_path / "sitecustomize.py").write_text("import sys\nsys.modules['pyvista'] = None\n")
    paths = [str(tmp_path), *filter(None, [os.environ.get("PYTHONPATH")])]
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join(paths))
    reason = mesh.rendering_status()
    assert reason.startswith(("ImportError", "ModuleNotFoundError")) and "pyvista" in reason
