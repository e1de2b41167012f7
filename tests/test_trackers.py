"""make_tracker and the trackers' failure handling: every method through the public interface on an
analytic room with known poses; diverging inputs (no depth, a different scene, an implausible jump)
are flagged with a reason and a finite fallback pose, never a crash or NaN."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import odometry_scene as scene
import pytest

from kintinuous_ref import se3
from kintinuous_ref.config import Config, with_overrides
from kintinuous_ref.errors import ConfigError
from kintinuous_ref.odometry import (
    METHODS,
    TrackingResult,
    is_repeated_frame,
    make_tracker,
    repeated_streams,
    stale_input,
)


@dataclass
class Model:
    """The fields of raycast.ModelPrediction the trackers read."""

    pose: np.ndarray
    vertices: np.ndarray
    normals: np.ndarray


def pose_error(estimate: np.ndarray, truth: np.ndarray) -> tuple[float, float]:
    difference = se3.inverse(truth) @ estimate
    return 1000 * float(np.linalg.norm(difference[:3, 3])), float(
        np.degrees(se3.rotation_angle(difference[:3, :3]))
    )


MOTION = se3.exp(np.array([0.01, -0.02, 0.015, 0.02, -0.01, 0.03]))


@pytest.fixture(scope="module")
def room():
    previous = scene.look_pose([0.1, -0.1, 0.2], 5, -10)
    current = previous @ MOTION
    vertices, normals = scene.model(previous, levels=1)[0]
    return (
        previous,
        current,
        scene.frame(previous),
        scene.frame(current),
        Model(previous, vertices, normals),
    )


def test_method_names():
    assert METHODS == (
        "icp",
        "rgbd",
        "fovis",
        "fovis/icp",
        "fovis/rgbd",
        "icp+rgbd",
        "fovis/icp+rgbd",
    )
    with pytest.raises(ConfigError, match="unknown odometry method 'kinfu'"):
        make_tracker("kinfu", Config(), scene.CAMERA)


@pytest.mark.parametrize("method", ["icp", "rgbd", "icp+rgbd"])
def test_dense_trackers_recover_a_known_motion(room, method):
    previous, current, previous_frame, current_frame, model = room
    result = make_tracker(method, Config(), scene.CAMERA).track(
        previous_frame, current_frame, model, previous
    )
    assert isinstance(result, TrackingResult)
    assert result.ok and result.reason == "" and result.used == method
    translation_mm, rotation_deg = pose_error(result.pose, current)
    assert translation_mm < 1.0 and rotation_deg < 0.1  # noise-free: 1 mm / 0.1 degree


def test_levels_end_early_at_the_configured_step(room, monkeypatch):
    # The default ends a level at a step under 10 um: fewer Gauss-Newton steps than every
    # iteration of 10/5/4, and a pose within that distance of the full schedule's.
    import kintinuous_ref.odometry as odometry

    previous, current, previous_frame, current_frame, model = room
    steps: list[int] = []

    def counted_refine(pose, system_at, *args):  # noqa: ANN001, ANN202
        def counted(level: int, estimate: np.ndarray):  # noqa: ANN202
            steps[-1] += 1
            return system_at(level, estimate)

        steps.append(0)
        return odometry.solve.refine(pose, counted, *args)

    monkeypatch.setattr(odometry, "refine", counted_refine)
    poses = []
    for converged_step in (Config().tracking.converged_step, 0.0):
        config = with_overrides(Config(), {"tracking.converged_step": converged_step})
        tracker = make_tracker("icp+rgbd", config, scene.CAMERA)
        result = tracker.track(previous_frame, current_frame, model, previous)
        assert result.ok
        poses.append(result.pose)
    assert Config().tracking.converged_step == 1e-5
    assert steps[1] == 19 and steps[0] < 19, steps
    translation_mm, rotation_deg = pose_error(poses[0], poses[1])
    assert translation_mm < 0.01 and rotation_deg < np.degrees(1e-5)


@pytest.mark.parametrize("method", ["fovis", "fovis/icp", "fovis/rgbd", "fovis/icp+rgbd"])
def test_fovis_trackers_follow_the_switching_rule(room, method):
    previous, current, previous_frame, current_frame, model = room
    result = make_tracker(method, Config(), scene.CAMERA).track(
        previous_frame, current_frame, model, previous
    )
    assert result.ok
    translation_mm, rotation_deg = pose_error(result.pose, current)
    if method == "fovis":
        assert result.used == "fovis"
        # Sparse corners on a 320x240 image: a few millimetres is what FOVIS can do.
        assert translation_mm < 10.0 and rotation_deg < 0.5
    else:
        # FOVIS and the dense estimator agree on the translation length far within mu = 3 cm,
        # so the paper's rule keeps the dense increment.
        assert result.used == method.partition("/")[2]
        assert translation_mm < 1.0 and rotation_deg < 0.1


def test_fovis_wins_when_the_lengths_disagree(room):
    # With mu = 0 any difference in translation length hands the increment to FOVIS.
    previous, _, previous_frame, current_frame, model = room
    config = with_overrides(Config(), {"fovis.switch_threshold": 0.0})
    result = make_tracker("fovis/icp", config, scene.CAMERA).track(
        previous_frame, current_frame, model, previous
    )
    assert result.ok and result.used == "fovis"


@pytest.mark.parametrize("method", ["icp", "rgbd", "icp+rgbd"])
def test_a_frame_without_depth_is_flagged(room, method):
    previous, _, previous_frame, current_frame, model = room
    empty = scene.Frame(
        [
            scene.Level(
                level.camera,
                np.zeros_like(level.depth),
                np.full_like(level.vertices, np.nan),
                np.full_like(level.normals, np.nan),
                level.intensity,
                level.intensity_dx,
                level.intensity_dy,
            )
            for level in current_frame.levels
        ]
    )
    result = make_tracker(method, Config(), scene.CAMERA).track(
        previous_frame, empty, model, previous
    )
    assert not result.ok
    assert "too few correspondences" in result.reason
    # No good increment yet: the fallback is the previous pose, finite.
    np.testing.assert_array_equal(result.pose, previous)


@pytest.mark.parametrize("method", ["icp", "rgbd", "icp+rgbd"])
def test_a_frame_of_another_scene_is_flagged(room, method):
    # The camera turned round by 150 degrees: nothing it sees overlaps the previous view.
    previous, _, previous_frame, _, model = room
    elsewhere = scene.frame(scene.look_pose([0.0, 0.0, 1.0], 150, 0))
    result = make_tracker(method, Config(), scene.CAMERA).track(
        previous_frame, elsewhere, model, previous
    )
    assert not result.ok and result.reason
    assert np.isfinite(result.pose).all()


def test_an_implausible_jump_is_flagged(room):
    # The true motion is 2.5 cm; a 1 cm limit makes it "implausible".
    previous, _, previous_frame, current_frame, model = room
    config = with_overrides(Config(), {"tracking.max_translation_jump": 0.01})
    result = make_tracker("icp", config, scene.CAMERA).track(
        previous_frame, current_frame, model, previous
    )
    assert not result.ok and "implausible jump" in result.reason


def test_missing_model_is_flagged_for_icp(room):
    previous, _, previous_frame, current_frame, _ = room
    result = make_tracker("icp+rgbd", Config(), scene.CAMERA).track(
        previous_frame, current_frame, None, previous
    )
    assert not result.ok and "no model" in result.reason


def test_constant_velocity_recovery(room):
    previous, current, previous_frame, current_frame, model = room
    tracker = make_tracker("icp", Config(), scene.CAMERA)
    good = tracker.track(previous_frame, current_frame, model, previous)
    assert good.ok
    increment = se3.inverse(previous) @ good.pose
    # The next frame has no depth: the pose continues with the last good increment ...
    blind = scene.Frame(
        [
            scene.Level(
                lv.camera,
                lv.depth * 0,
                lv.vertices * np.nan,
                lv.normals * np.nan,
                lv.intensity,
                lv.intensity_dx,
                lv.intensity_dy,
            )
            for lv in current_frame.levels
        ]
    )
    first = tracker.track(current_frame, blind, model, good.pose)
    assert not first.ok
    np.testing.assert_allclose(first.pose, good.pose @ increment, atol=1e-12)
    # ... and a second failure in a row holds still rather than extrapolating a guess.
    second = tracker.track(blind, blind, model, first.pose)
    assert not second.ok
    np.testing.assert_allclose(second.pose, first.pose, atol=1e-12)
    # With fallback "previous" the first failure already holds still.
    still = make_tracker(
        "icp", with_overrides(Config(), {"tracking.fallback": "previous"}), scene.CAMERA
    )
    assert still.track(previous_frame, current_frame, model, previous).ok
    np.testing.assert_array_equal(
        still.track(current_frame, blind, model, good.pose).pose, good.pose
    )


def test_command_line_offers_every_method_and_config_overrides(tmp_path):
    from kintinuous_ref.program import cli

    assert cli.ODOMETRY_CHOICES == ("groundtruth", *METHODS)
    args = cli.build_parser().parse_args(
        ["reconstruct", "desk", "--out", str(tmp_path), "--odometry", "fovis/icp+rgbd"]
    )
    assert args.odometry == "fovis/icp+rgbd"
    config_file = tmp_path / "config.json"
    config_file.write_text('{"icp": {"iterations": [5, 3, 2]}, "combined.rgbd_weight": 0.5}')
    config = cli.configured(
        Config(), config_file, ["combined.weighting=original-code", "combined.rgbd_weight=0.2"]
    )
    assert config.icp.iterations == (5, 3, 2)
    assert config.combined.weighting == "original-code"
    assert config.combined.rgbd_weight == 0.2  # --set wins over the file
    with pytest.raises(ConfigError, match="unknown configuration key"):
        cli.configured(Config(), None, ["icp.nonsense=1"])


@pytest.mark.parametrize("method", ["icp", "rgbd", "icp+rgbd"])
def test_a_repeated_frame_is_a_failure_with_its_reason(room, method):
    # The same images twice (7-Scenes redkitchen repeats 12 of its frames 228-298): no new
    # measurement, so no estimate: a failure that says why, whose pose is the fallback's (here
    # the previous pose: the tracker has no motion to repeat yet), never a silently frozen pose.
    previous, _, previous_frame, _, model = room
    tracker = make_tracker(method, Config(), scene.CAMERA)
    result = tracker.track(previous_frame, previous_frame, model, previous)
    assert not result.ok
    assert "repeat the previous frame's: no new measurement" in result.reason
    np.testing.assert_array_equal(result.pose, previous)
    assert is_repeated_frame(previous_frame, previous_frame)
    assert not is_repeated_frame(previous_frame, room[3])
    assert not is_repeated_frame(None, previous_frame)


@pytest.mark.parametrize(
    ("method", "stream", "fails"),
    [
        ("rgbd", "colour", True),
        ("icp", "depth", True),
        ("rgbd", "depth", False),
        ("icp", "colour", False),
        ("icp+rgbd", "colour", False),
        ("icp+rgbd", "depth", False),
    ],
)
def test_a_tracker_without_a_fresh_image_says_so(method, stream, fails):
    reason = stale_input(method, stream == "depth", stream == "colour")
    assert bool(reason) == fails
    if fails:
        assert f"the {stream} image repeats" in reason


def stale(current: scene.Frame, previous: scene.Frame, stream: str) -> scene.Frame:
    """The current frame with one stream ("colour" or "depth") repeated from the previous one."""
    levels = []
    for now, before in zip(current.levels, previous.levels, strict=True):
        geometry = before if stream == "depth" else now
        photometry = before if stream == "colour" else now
        levels.append(
            scene.Level(
                now.camera,
                geometry.depth,
                geometry.vertices,
                geometry.normals,
                photometry.intensity,
                photometry.intensity_dx,
                photometry.intensity_dy,
            )
        )
    return scene.Frame(levels)


@pytest.mark.parametrize(
    ("stream", "tolerance_mm"),
    # Stale colour: ICP alone, as exact as in the noise-free test above (measured 1e-5 mm).
    # Stale depth: RGB-D alone, its interest points back-projected with the previous view's
    # depth (measured 0.9 mm). Using the stale stream as well ends 37 mm from the truth.
    [("colour", 1.0), ("depth", 3.0)],
)
def test_a_stale_stream_is_left_out_of_icp_rgbd(room, stream, tolerance_mm):
    # The camera moved (MOTION: 3.7 cm, 2 degrees) but one sensor stream repeated its last image,
    # which says "no motion"; icp+rgbd tracks on the fresh stream alone for that frame.
    previous, current, previous_frame, current_frame, model = room
    frame = stale(current_frame, previous_frame, stream)
    assert repeated_streams(previous_frame, frame) == (stream == "depth", stream == "colour")
    result = make_tracker("icp+rgbd", Config(), scene.CAMERA).track(
        previous_frame, frame, model, previous
    )
    assert result.ok
    translation_mm, _ = pose_error(result.pose, current)
    assert translation_mm < tolerance_mm
