"""The pipeline on the cpu backend against the reference backend: a short run of the synthetic
desk at 160x120 into a 64^3 moving volume, with ground-truth poses and with ICP+RGB-D tracking.

Tolerances: the volumes differ only by the int16/uint8 rounding (<= 0.5 n / 32767 in F after n
frames, tests/fast_equivalence.py) and the fast trackers' sums by float rounding; so tracked
poses agree to 0.1 mm / 0.01 degree, and the meshes' vertices to a hair of a voxel (marching
cubes edge crossings move by voxel * dF / |F1 - F0|): every cpu vertex within 1 mm of a reference
vertex."""

import numpy as np
import pytest
from scipy.spatial import cKDTree

from kintinuous_fast import load_backend
from kintinuous_ref import pipeline, se3
from kintinuous_ref.config import Config, VolumeConfig
from kintinuous_ref.datasets.synthetic import make_scenario
from kintinuous_ref.datasets.tum import Frame

FRAMES = 6


@pytest.fixture(scope="module")
def desk():
    return make_scenario("desk", frames=FRAMES, width=160, height=120)


def run(desk, odometry: str, backend: str) -> pipeline.PipelineResult:
    frames = []
    for index in range(FRAMES):
        colour, depth = desk.render(index)
        frames.append(Frame(index, float(desk.trajectory.timestamps[index]), colour, depth))
    config = Config(volume=VolumeConfig(resolution=64, size=2.0, shift_threshold=2))
    return pipeline.run(
        frames,
        desk.camera,
        config,
        odometry,
        desk.trajectory,
        backend=load_backend(backend),
        predict_model=True,
    )


@pytest.mark.parametrize("odometry", ["groundtruth", "icp+rgbd"])
def test_pipeline_equivalence_cpu_vs_ref(desk, odometry):
    want, got = run(desk, odometry, "ref"), run(desk, odometry, "cpu")
    assert got.tracking_failures == want.tracking_failures == 0
    for a, b in zip(got.poses, want.poses, strict=True):
        delta = se3.inverse(b) @ a
        assert np.linalg.norm(delta[:3, 3]) < 1e-4
        assert np.degrees(se3.rotation_angle(delta[:3, :3])) < 1e-2
    if odometry != "groundtruth":  # the tracker really moved away from the first pose
        truth = desk.trajectory.poses[FRAMES - 1]
        assert np.linalg.norm(want.poses[-1][:3, 3] - truth[:3, 3]) < 0.02
    assert got.shifts == want.shifts
    np.testing.assert_allclose(got.volume.origin, want.volume.origin, atol=1e-9)
    got.moving.finish()
    want.moving.finish()
    points_got = np.concatenate([m.points for m in got.moving.store])
    points_want = np.concatenate([m.points for m in want.moving.store])
    assert len(points_want) > 500
    assert abs(len(points_got) - len(points_want)) <= 0.01 * len(points_want)
    distance, _ = cKDTree(points_want).query(points_got)
    assert distance.max() < 1e-3
