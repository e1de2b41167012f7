"""FOVIS over large motions (frames far apart in time), and the switching that relies on it.

The truths are the synthetic scenes' exact poses (and redkitchen's ground truth where present).
Before the coarse-to-fine initial rotation and the guided second matching pass (odometry/fovis.py,
fovis_features.py), FOVIS reported failure on most views below: the 12 degree pan (so the
switching fell back to a lost ICP+RGB-D), the 10 degree tilt with a forward step, every step of
the `loop` path at 2 Hz from frame 180 on, 3 of 14 redkitchen steps; its initial rotation of a
15 degree pan was 13 degrees off. Only the 15 cm, 7.6 degree step about all axes it managed.
"""

import numpy as np
import pytest

from kintinuous_ref import se3
from kintinuous_ref.camera import Intrinsics
from kintinuous_ref.config import Config, FovisConfig, PreprocessConfig
from kintinuous_ref.datasets import real_dataset
from kintinuous_ref.datasets.synthetic import make_scenario
from kintinuous_ref.datasets.tum import open_sequence
from kintinuous_ref.odometry import fovis, make_tracker, switching
from kintinuous_ref.preprocess import preprocess_frame


def pose_error(estimate: np.ndarray, truth: np.ndarray) -> tuple[float, float]:
    """Translation (mm) and rotation (deg) of `estimate` relative to `truth`."""
    difference = se3.inverse(truth) @ estimate
    return 1000 * float(np.linalg.norm(difference[:3, 3])), float(
        np.degrees(se3.rotation_angle(difference[:3, :3]))
    )


def preprocess_view(scenario, pose, noise=None):
    colour, depth = scenario.render_at(pose, noise=noise)
    return preprocess_frame(colour, depth, scenario.camera, PreprocessConfig())


@pytest.fixture(scope="module")
def desk():
    """The furnished room without sensor noise, 640x480, and its first view."""
    scenario = make_scenario("desk", frames=30, noise=False)
    start = scenario.trajectory.poses[0]
    return scenario, start, preprocess_view(scenario, start)


# Twists (rotation, then translation): 1-2 frames of a 10-15 cm, 10-12 degree step at 30 Hz are
# 0.3-0.5 s of a brisk hand-held motion.
LARGE_MOTIONS = {
    "12 deg pan, 10 cm sideways": [0.0, 0.21, 0.0, 0.10, 0.0, 0.0],
    "10 deg tilt, 15 cm forward": [0.17, 0.0, 0.0, 0.0, 0.0, 0.15],
    "15 cm and 7.6 deg about all axes": [0.05, -0.12, 0.03, 0.12, -0.05, 0.08],
}


@pytest.mark.parametrize("twist", LARGE_MOTIONS.values(), ids=LARGE_MOTIONS.keys())
def test_a_large_step_is_recovered(desk, twist):
    scenario, start, first = desk
    increment = se3.exp(np.array(twist))
    second = preprocess_view(scenario, start @ increment)
    result = fovis.estimate_motion(first, second, scenario.camera, FovisConfig())
    assert result.ok, result.reason
    translation_mm, rotation_deg = pose_error(result.increment, increment)
    # Noise-free renders: corner quantisation and texture interpolation only (measured: under
    # 0.5 mm and 0.02 deg with about 200 inliers); the bound leaves room for other platforms.
    assert result.inliers >= 100
    assert translation_mm < 2.0
    assert rotation_deg < 0.1


def test_the_initial_rotation_finds_a_large_pan(desk):
    """A 15 degree pan moves the 80x60 image by 20 px: the grid and coarse-to-fine search find
    it where Gauss-Newton from the identity did not (it came back 9 degrees short on redkitchen)."""
    scenario, start, first = desk
    pan = se3.exp(np.array([0.0, np.radians(15.0), 0.0, 0.0, 0.0, 0.0]))
    second = preprocess_view(scenario, start @ pan)
    coarsest = len(first.levels) - 1
    rotation = fovis.estimate_initial_rotation(
        first.levels[coarsest].intensity,
        second.levels[coarsest].intensity,
        scenario.camera.at_level(coarsest),
    )
    # 80x60 pixels of 0.9 degrees each: the estimate is good to a fraction of a pixel.
    assert np.degrees(se3.rotation_angle(rotation.T @ pan[:3, :3])) < 0.5


def test_prediction_under_a_full_motion_is_the_projection():
    """predict_pixels_with_motion against the pinhole projection written out by hand."""
    camera = Intrinsics(500.0, 500.0, 320.0, 240.0, 640, 480)
    points = np.array([[0.2, -0.1, 2.0], [-0.5, 0.3, 1.5]])
    increment = se3.exp(np.array([0.02, -0.1, 0.05, 0.1, 0.02, -0.05]))
    features = fovis.Features(
        levels=np.array([0, 1]),
        pixels=np.zeros((2, 2)),
        points=points,
        descriptors=np.zeros((2, 81), np.float32),
        responses=np.zeros(2, np.float32),
    )
    predicted = fovis.predict_pixels_with_motion(features, increment, camera)
    for k, point in enumerate(points):
        x, y, z = se3.inverse(increment)[:3, :3] @ point + se3.inverse(increment)[:3, 3]
        expected = np.array([500.0 * x / z + 320.0, 500.0 * y / z + 240.0]) / 2**k
        np.testing.assert_allclose(predicted[k], expected, atol=1e-9)


def test_the_loop_path_at_two_hertz_is_tracked():
    """Every 15th frame of the `loop` path with sensor noise, frames 180-285: 7 steps of 23-27 cm
    turning 6-12 degrees each. FOVIS alone tracks all of them (before: none)."""
    scenario = make_scenario("loop", frames=300, noise=True)
    indices = range(180, 300, 15)
    frames = [preprocess_view(scenario, scenario.trajectory.poses[i], noise=True) for i in indices]
    poses = scenario.trajectory.poses[list(indices)]
    pose = poses[0]
    for k in range(1, len(frames)):
        result = fovis.estimate_motion(frames[k - 1], frames[k], scenario.camera, FovisConfig())
        assert result.ok, f"step {k}: {result.reason}"
        truth = se3.inverse(poses[k - 1]) @ poses[k]
        translation_mm, rotation_deg = pose_error(result.increment, truth)
        # Kinect-like noise on depth and colour (measured: 0.4-1.6 mm, under 0.03 deg a step).
        assert translation_mm < 5.0 and rotation_deg < 0.1, k
        pose = pose @ result.increment
    translation_mm, rotation_deg = pose_error(pose, poses[-1])
    assert translation_mm < 15.0 and rotation_deg < 0.3


def test_switching_takes_fovis_when_the_dense_estimate_is_lost():
    """Paper V-A: the FOVIS increment is used when the translation lengths differ by more than
    mu = 3 cm. On a 12 degree pan with a 10 cm step ICP+RGB-D from the previous pose converges to
    a wrong motion (tens of centimetres off); `fovis/icp+rgbd` must take FOVIS's increment and
    land on the true pose."""
    scenario = make_scenario("desk", frames=30, noise=True)
    start = scenario.trajectory.poses[0]
    increment = se3.exp(np.array(LARGE_MOTIONS["12 deg pan, 10 cm sideways"]))
    first = preprocess_view(scenario, start)
    second = preprocess_view(scenario, start @ increment)
    model = model_from_frame(first, start)
    config = Config()

    dense = make_tracker("icp+rgbd", config, scenario.camera).track(first, second, model, start)
    switched = make_tracker("fovis/icp+rgbd", config, scenario.camera).track(
        first, second, model, start
    )
    sparse = fovis.estimate_motion(first, second, scenario.camera, config.fovis)

    assert sparse.ok, sparse.reason
    dense_increment = se3.inverse(start) @ dense.pose
    _, chosen = switching.choose_increment(
        sparse.increment, dense_increment, config.fovis.switch_threshold
    )
    assert chosen == switching.FOVIS  # the lengths disagree by more than mu
    assert pose_error(dense.pose, start @ increment)[0] > 30.0  # the dense estimate is lost
    assert switched.ok and switched.used == "fovis"
    translation_mm, rotation_deg = pose_error(switched.pose, start @ increment)
    # Sensor noise on depth and colour (measured: 0.4 mm, 0.01 deg).
    assert translation_mm < 3.0 and rotation_deg < 0.1


class _Model:
    """What the dense trackers read of a raycast model: its pose and world-frame vertices and
    normals at full resolution (here the previous frame's own, as a perfect raycast gives)."""

    def __init__(self, pose: np.ndarray, vertices: np.ndarray, normals: np.ndarray) -> None:
        self.pose, self.vertices, self.normals = pose, vertices, normals


def model_from_frame(frame, pose: np.ndarray) -> _Model:
    level = frame.levels[0]
    rotation, translation = pose[:3, :3], pose[:3, 3]
    vertices = np.asarray(level.vertices, np.float64) @ rotation.T + translation
    normals = np.asarray(level.normals, np.float64) @ rotation.T
    return _Model(pose, vertices.astype(np.float32), normals.astype(np.float32))


@pytest.mark.realdata
@pytest.mark.skipif(real_dataset("redkitchen") is None, reason="redkitchen not present")
def test_redkitchen_every_twentieth_frame():
    """Frames 0, 20, ..., 280 of redkitchen (0.67 s apart: up to 20 cm and 14 degrees a step).
    FOVIS failed on 3 of the 14 steps before; now on at most 1, and each step it reports is
    within 6 cm and 3.5 degrees of the ground truth (measured: at most 4.6 cm and 3.0 degrees;
    7-Scenes' ground truth is good to about a centimetre and its depth is not registered to the
    colour, which shifts each corner's 3D point)."""
    sequence = open_sequence(real_dataset("redkitchen"))
    truth = sequence.groundtruth_for_frames().poses
    indices = list(range(0, 300, 20))
    frames = [
        preprocess_frame(sequence[i].colour, sequence[i].depth, sequence.camera, PreprocessConfig())
        for i in indices
    ]
    failures = 0
    for k in range(1, len(frames)):
        result = fovis.estimate_motion(frames[k - 1], frames[k], sequence.camera, FovisConfig())
        if not result.ok:
            failures += 1
            continue
        step = se3.inverse(truth[indices[k - 1]]) @ truth[indices[k]]
        translation_mm, rotation_deg = pose_error(result.increment, step)
        assert translation_mm < 60.0 and rotation_deg < 3.5, indices[k]
    assert failures <= 1
