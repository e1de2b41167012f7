"""Raycasting against analytic geometry: a fused box must come back at the box's exact depth,
with the faces' normals and colours; empty-space skipping must not change a single ray."""

import numpy as np
import pytest
from mapping_scene import CAMERA, BoxScene, away_from_edges, pose, rotation

from kintinuous_ref import raycast, tsdf
from kintinuous_ref.config import VolumeConfig

FUSE_POSES = [
    pose(np.eye(3), [0.0, 0.0, 0.0]),
    pose(rotation("y", 5.0), [0.05, 0.0, 0.02]),
    pose(rotation("x", -4.0), [-0.04, 0.03, 0.0]),
]
VIEW = pose(rotation("y", 2.0), [0.01, 0.01, 0.01])  # a pose none of the frames was taken from


@pytest.fixture(scope="module")
def fused_box():
    scene = BoxScene()
    volume = tsdf.make_volume(VolumeConfig(resolution=96, size=1.0), FUSE_POSES[0])
    for camera_pose in FUSE_POSES:
        depth, surface, _, _ = scene.cast(camera_pose)
        tsdf.integrate(volume, depth, camera_pose, CAMERA, scene.colour(surface))
    return scene, volume, raycast.raycast(volume, VIEW, CAMERA)


def camera_depth(prediction: raycast.ModelPrediction) -> np.ndarray:
    local = (prediction.vertices.reshape(-1, 3) - prediction.pose[:3, 3]) @ prediction.pose[:3, :3]
    return local[:, 2].reshape(CAMERA.height, CAMERA.width)


def test_raycast_of_a_fused_box_matches_its_analytic_depth(fused_box):
    scene, volume, prediction = fused_box
    depth, surface, normals, _ = scene.cast(VIEW)
    rays = CAMERA.ray_directions() @ VIEW[:3, :3].T
    rays /= np.linalg.norm(rays, axis=-1, keepdims=True)
    incidence = np.degrees(np.arccos(np.clip(-(rays * normals).sum(-1), -1, 1)))
    # Away from edges (4 px ~ 1 voxel at 0.5 m) and for faces seen within 60 degrees of
    # head-on: a projective TSDF measures distance along the ray, which at grazing angles is
    # far from the distance to the surface (box faces at 72-79 degrees are excluded here).
    good = away_from_edges(surface, 4) & (incidence < 60)
    assert good.sum() > 8000
    error = np.abs(camera_depth(prediction) - depth)[good]
    assert np.isnan(error).mean() < 1e-3  # the surface is found on every such ray
    # Tolerances: a 10.4 mm voxel, linear interpolation of the crossing and the pixel rounding
    # of lambda in integration give sub-millimetre errors on planes.
    assert np.nanmedian(error) < 0.5e-3
    assert np.nanpercentile(error, 99) < 3e-3
    angle = np.degrees(np.arccos(np.clip((prediction.normals * normals).sum(-1), -1, 1)))[good]
    assert np.nanmedian(angle) < 2.0  # central differences of the TSDF over one voxel
    assert np.nanpercentile(angle, 90) < 8.0


def test_raycast_colours_and_world_frame(fused_box):
    scene, _, prediction = fused_box
    _, surface, _, _ = scene.cast(VIEW)
    good = away_from_edges(surface, 4)
    np.testing.assert_array_equal(
        prediction.colours[good & (surface == 0)],
        np.broadcast_to(scene.wall_colour, ((good & (surface == 0)).sum(), 3)),
    )
    box = good & (surface >= 1)
    assert (prediction.colours[box] == scene.box_colour).all(axis=1).mean() > 0.99
    # World frame: the wall's vertices sit at world z = 0.85 whatever the viewing pose.
    wall_z = prediction.vertices[good & (surface == 0)][:, 2]
    assert np.abs(wall_z - 0.85).max() < 2e-3
    np.testing.assert_array_equal(prediction.pose, VIEW)


def test_skipping_empty_space_changes_nothing(fused_box):
    _, volume, prediction = fused_box
    plain = raycast.raycast(volume, VIEW, CAMERA, skip_empty=False)
    np.testing.assert_array_equal(plain.vertices, prediction.vertices)
    np.testing.assert_array_equal(plain.normals, prediction.normals)


def test_raycast_without_colour_keeps_the_geometry(fused_box):
    _, volume, prediction = fused_box
    uncoloured = raycast.raycast(volume, VIEW, CAMERA, colour=False)
    np.testing.assert_array_equal(uncoloured.vertices, prediction.vertices)
    np.testing.assert_array_equal(uncoloured.normals, prediction.normals)
    assert prediction.colours.any() and not uncoloured.colours.any()


@pytest.mark.parametrize("stride", [2, 3])
def test_raycast_stride_casts_only_the_pixels_a_pyramid_level_reads(fused_box, stride):
    """With a stride only the pixels (s u, s v) are cast (the fast-odometry setting's model
    pyramid starts at level 1: preprocess.model_pyramid keeps exactly those), each as in the
    full raycast; every other pixel stays empty."""
    _, volume, prediction = fused_box
    strided = raycast.raycast(volume, VIEW, CAMERA, stride=stride)
    cast = np.zeros((CAMERA.height, CAMERA.width), dtype=bool)
    cast[::stride, ::stride] = True
    np.testing.assert_array_equal(strided.vertices[cast], prediction.vertices[cast])
    np.testing.assert_array_equal(strided.normals[cast], prediction.normals[cast])
    np.testing.assert_array_equal(strided.colours[cast], prediction.colours[cast])
    assert np.isfinite(strided.vertices[cast]).mean() > 0.5
    assert np.isnan(strided.vertices[~cast]).all() and not strided.colours[~cast].any()
    for bad in (0, -2, 1.5, True):
        with pytest.raises(ValueError, match="stride must be a whole number"):
            raycast.raycast(volume, VIEW, CAMERA, stride=bad)


def test_raycast_from_outside_the_volume(fused_box):
    scene, volume, _ = fused_box
    behind = pose(np.eye(3), [0.0, 0.0, -0.4])  # 0.4 m behind the volume's front face
    prediction = raycast.raycast(volume, behind, CAMERA)
    depth, surface, _, _ = scene.cast(behind)
    good = away_from_edges(surface, 3) & (surface == 0)
    error = np.abs(camera_depth(prediction) - depth)[good]
    assert np.nanmedian(error) < 1e-3
    away = pose(rotation("y", 180.0), [0.0, 0.0, -0.4])  # looking away from the volume
    assert np.isnan(raycast.raycast(volume, away, CAMERA).vertices).all()


def test_raycast_of_an_empty_volume_finds_nothing():
    volume = tsdf.make_volume(VolumeConfig(resolution=32, size=1.0), np.eye(4))
    prediction = raycast.raycast(volume, np.eye(4), CAMERA)
    assert np.isnan(prediction.vertices).all() and np.isnan(prediction.normals).all()
    assert (prediction.colours == 0).all()
    assert prediction.vertices.dtype == np.float32 and prediction.vertices.shape == (120, 160, 3)


def test_back_faces_are_not_surfaces():
    # A camera inside the box (behind its front face) sees only back faces: no surface.
    scene = BoxScene(rot=np.eye(3), centre=(0.0, 0.0, 0.5), half=(0.3, 0.3, 0.1))
    volume = tsdf.make_volume(VolumeConfig(resolution=64, size=1.0), np.eye(4))
    depth, surface, _, _ = scene.cast(np.eye(4))
    tsdf.integrate(volume, depth, np.eye(4), CAMERA)
    from_behind = pose(rotation("y", 180.0), [0.0, 0.0, 0.95])  # beyond the box, looking back
    prediction = raycast.raycast(volume, from_behind, CAMERA)
    assert np.isnan(prediction.vertices).all()
