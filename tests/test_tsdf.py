"""TSDF integration against closed forms: a plane at a known distance, the running average and
its cap, occlusion, placement, degenerate frames and the up-front volume checks."""

import numpy as np
import pytest
from mapping_scene import CAMERA, pose, rotation

from kintinuous_ref import tsdf
from kintinuous_ref.config import VolumeConfig
from kintinuous_ref.errors import ConfigError

CONFIG = VolumeConfig(resolution=64, size=1.0)  # 15.6 mm voxels, truncation 31 mm (2 voxels)


def plane_depth(distance: float) -> np.ndarray:
    return np.full((CAMERA.height, CAMERA.width), distance, np.float32)


def zero_crossing_along(volume: tsdf.TsdfVolume, i: int, j: int) -> float:
    """z (world) where the TSDF column (i, j, :) changes sign, by linear interpolation."""
    column, weight = volume.tsdf[i, j], volume.weight[i, j]
    k = np.flatnonzero((column[:-1] > 0) & (column[1:] < 0) & (weight[:-1] > 0) & (weight[1:] > 0))
    assert len(k) == 1
    k = k[0]
    z0 = volume.origin[2] + k * volume.voxel_size
    return z0 + volume.voxel_size * column[k] / (column[k] - column[k + 1])


def test_plane_at_known_distance_gives_the_zero_crossing():
    volume = tsdf.make_volume(CONFIG, np.eye(4))
    tsdf.integrate(volume, plane_depth(0.6), np.eye(4), CAMERA)
    # Near the optical axis the ray distance to the plane is (0.6 - z) |p| / z: every voxel in
    # the band holds it / truncation. Pixel rounding of lambda costs < 0.6 * 1e-3 m here.
    i, j = 31, 32  # the column nearest the optical axis (x = -7.8 mm, y = +7.8 mm)
    centres = volume.voxel_to_world(np.array([[i, j, k] for k in range(64)], float))
    distance = np.linalg.norm(centres, axis=1)
    expected = (0.6 * distance / centres[:, 2] - distance) / volume.truncation
    band = volume.weight[i, j] > 0
    np.testing.assert_allclose(volume.tsdf[i, j][band], np.minimum(1, expected[band]), atol=0.02)
    assert abs(zero_crossing_along(volume, i, j) - 0.6) < 1e-3
    # Everywhere in the image the crossing is at z = 0.6 within 1 mm.
    for i, j in [(20, 25), (40, 40), (32, 20)]:
        assert abs(zero_crossing_along(volume, i, j) - 0.6) < 1e-3


def test_plane_from_a_moved_camera_lands_in_world_coordinates():
    # Camera 0.1 m to the left and 0.05 m back, turned 10 degrees about y; the wall z = 0.7
    # (world) is fused from there and must appear at world z = 0.7.
    first = np.eye(4)
    camera_pose = pose(rotation("y", 10.0), [-0.1, 0.0, -0.05])
    rays = CAMERA.ray_directions() @ camera_pose[:3, :3].T
    depth = ((0.7 - camera_pose[2, 3]) / rays[..., 2]).astype(np.float32)  # camera z per pixel
    volume = tsdf.make_volume(CONFIG, first)
    tsdf.integrate(volume, depth, camera_pose, CAMERA)
    for i, j in [(30, 30), (36, 28)]:
        assert abs(zero_crossing_along(volume, i, j) - 0.7) < 1.5e-3


def test_running_average_and_weight_cap():
    volume = tsdf.make_volume(VolumeConfig(resolution=64, size=1.0, max_weight=3), np.eye(4))
    tsdf.integrate(volume, plane_depth(0.6), np.eye(4), CAMERA)
    first = volume.tsdf.copy()
    tsdf.integrate(volume, plane_depth(0.62), np.eye(4), CAMERA)
    single = tsdf.make_volume(CONFIG, np.eye(4))
    tsdf.integrate(single, plane_depth(0.62), np.eye(4), CAMERA)
    both = (single.weight > 0) & (volume.weight == 2)
    # Two observations of weight 1: the mean of the two truncated distances.
    np.testing.assert_allclose(volume.tsdf[both], (first[both] + single.tsdf[both]) / 2, atol=1e-6)
    for _ in range(4):
        tsdf.integrate(volume, plane_depth(0.6), np.eye(4), CAMERA)
    assert volume.weight.max() == 3.0


def test_voxels_behind_the_band_are_not_touched():
    volume = tsdf.make_volume(CONFIG, np.eye(4))
    tsdf.integrate(volume, plane_depth(0.6), np.eye(4), CAMERA)
    centres_z = volume.origin[2] + np.arange(64) * volume.voxel_size
    behind = centres_z > 0.6 + volume.truncation + 1e-3
    assert volume.weight[32, 32, behind].max() == 0
    # Free space in front is +1 (the first voxels, 8 mm from the camera, lie outside the view).
    in_front = (centres_z < 0.5) & (centres_z > 0.05)
    assert volume.tsdf[32, 32, in_front].min() == 1.0 and volume.weight[32, 32, in_front].min() == 1


def test_colour_is_fused_near_the_surface_with_its_weight():
    volume = tsdf.make_volume(CONFIG, np.eye(4))
    colour = np.zeros((CAMERA.height, CAMERA.width, 3), np.uint8)
    colour[...] = (10, 200, 30)
    weights = np.full(colour.shape[:2], 0.5, np.float32)
    weights[:, :80] = 0.0  # left half: no colour update
    tsdf.integrate(volume, plane_depth(0.6), np.eye(4), CAMERA, colour, weights)
    coloured = volume.colour_weight > 0
    np.testing.assert_allclose(
        volume.colour[coloured], np.broadcast_to([10, 200, 30], (coloured.sum(), 3))
    )
    np.testing.assert_allclose(volume.colour_weight[coloured], 0.5)
    z = volume.origin[2] + np.arange(64) * volume.voxel_size
    assert np.all(np.abs(z[np.flatnonzero(coloured.any(axis=(0, 1)))] - 0.6) < volume.truncation)
    x = volume.origin[0] + np.arange(64) * volume.voxel_size
    assert x[np.flatnonzero(coloured.any(axis=(1, 2)))].min() > -volume.voxel_size


def test_all_zero_depth_and_camera_outside_change_nothing():
    volume = tsdf.make_volume(CONFIG, np.eye(4))
    tsdf.integrate(volume, np.zeros((120, 160), np.float32), np.eye(4), CAMERA)
    assert volume.weight.max() == 0
    away = pose(rotation("y", 180.0), [0.0, 0.0, -0.5])  # behind the volume, looking away
    tsdf.integrate(volume, plane_depth(1.0), away, CAMERA)
    assert volume.weight.max() == 0
    # From outside, looking in: the wall 1.2 m ahead is at world z = 0.7.
    outside = pose(np.eye(3), [0.0, 0.0, -0.5])
    tsdf.integrate(volume, plane_depth(1.2), outside, CAMERA)
    assert abs(zero_crossing_along(volume, 32, 32) - 0.7) < 1e-3


def test_placement_ahead_and_centred():
    first = pose(rotation("x", 90.0), [1.0, 2.0, 3.0])  # optical axis along world -y
    ahead = tsdf.make_volume(CONFIG, first)
    centre = ahead.origin + 0.5 * (ahead.resolution - 1) * ahead.voxel_size
    np.testing.assert_allclose(centre, [1.0, 2.0 - 0.5, 3.0], atol=1e-12)
    centred = tsdf.make_volume(VolumeConfig(resolution=64, size=1.0, placement="centred"), first)
    np.testing.assert_allclose(
        centred.origin + 0.5 * 63 * centred.voxel_size, [1.0, 2.0, 3.0], atol=1e-12
    )


def test_trilinear_is_exact_on_linear_fields():
    grid = np.fromfunction(lambda i, j, k: 2 * i - j + 0.5 * k, (8, 8, 8)).astype(np.float32)
    points = np.random.default_rng(1).uniform(0, 7, (100, 3))
    expected = 2 * points[:, 0] - points[:, 1] + 0.5 * points[:, 2]
    np.testing.assert_allclose(tsdf.trilinear(grid, points), expected, atol=1e-4)


def test_bad_volumes_are_refused_up_front(monkeypatch):
    # A config's own fields are checked when it is made; the volume's memory by the backend.
    with pytest.raises(ConfigError, match="size must be positive"):
        VolumeConfig(size=0.0)
    with pytest.raises(ConfigError, match="size must be positive"):
        VolumeConfig(size=-3.0)
    with pytest.raises(ConfigError, match="resolution"):
        VolumeConfig(resolution=0)
    with pytest.raises(ConfigError, match="placement"):
        VolumeConfig(placement="left")
    monkeypatch.setattr(tsdf, "available_memory_bytes", lambda: 2 << 30)
    # 512^3 with colour: 24 bytes per voxel = 3 GiB > 2 GiB.
    with pytest.raises(ConfigError, match=r"needs 3\.0 GiB but only 2\.0 GiB"):
        tsdf.make_volume(VolumeConfig(resolution=512, size=6.0), np.eye(4))
    assert tsdf.memory_bytes(VolumeConfig(resolution=256, colour=False)) == 8 * 256**3
