"""Place recognition on the loop-closure scenarios: a true revisit is found and measured, two
identical bays in different places are not taken for one."""

from __future__ import annotations

from dataclasses import replace
from functools import cache

import numpy as np
import pytest

from kintinuous_ref import se3
from kintinuous_ref.config import Config, LoopClosureConfig
from kintinuous_ref.datasets import synthetic
from kintinuous_ref.datasets.synthetic.revisits import REVISIT_LAP_SECONDS, TWINS_BAYS, TWINS_SPEED
from kintinuous_ref.datasets.synthetic.trajectories import FRAME_RATE
from kintinuous_ref.loop_closure import keyframes, place_recognition
from kintinuous_ref.preprocess import preprocess_frame

SETTINGS = LoopClosureConfig()


@cache
def scenario(name: str) -> synthetic.Scenario:
    return synthetic.make_scenario(name, frames=480, width=320, height=240)


def keyframe(
    name: str, frame: int, node: int, pose: np.ndarray | None = None
) -> keyframes.Keyframe:
    """A keyframe of a scenario frame at its true pose (or `pose`)."""
    s = scenario(name)
    colour, depth = s.render(frame)
    preprocessed = preprocess_frame(colour, depth, s.camera, Config().preprocess)
    pose = s.trajectory.poses[frame] if pose is None else pose
    return keyframes.make_keyframe(node, frame, pose, 0.0, preprocessed, SETTINGS)


def test_keyframes_are_taken_by_distance_or_angle():
    start = np.eye(4)
    assert keyframes.is_new_keyframe(None, start, SETTINGS)
    assert not keyframes.is_new_keyframe(start, se3.exp(np.array([0, 0, 0, 0.2, 0, 0])), SETTINGS)
    assert keyframes.is_new_keyframe(start, se3.exp(np.array([0, 0, 0, 0.31, 0, 0])), SETTINGS)
    assert keyframes.is_new_keyframe(start, se3.exp(np.array([0, 0.27, 0, 0, 0, 0])), SETTINGS)


def test_ransac_finds_a_rigid_motion_among_outliers():
    rng = np.random.default_rng(4)
    source = rng.uniform(-1, 1, (60, 3)) + [0, 0, 2]
    motion = se3.exp(np.array([0.1, -0.2, 0.05, 0.3, 0.0, -0.1]))
    target = se3.transform_points(motion, source)
    target[:20] = rng.uniform(-1, 1, (20, 3))  # a third are wrong matches
    found, inliers = place_recognition.ransac_rigid(source, target, 200, 0.02, rng)
    np.testing.assert_allclose(found, motion, atol=1e-9)
    assert inliers.sum() == 40 and not inliers[:20].any()


def test_a_true_revisit_is_accepted_with_its_true_relative_pose():
    """Frame 0 and the same place one lap later (the `revisit` path repeats exactly, the hand
    tremor does not), the later one at a pose drifted by 20 cm and 3 degrees."""
    lap = int(REVISIT_LAP_SECONDS * FRAME_RATE)
    old = keyframe("revisit", 0, 0)
    truth = scenario("revisit").trajectory.poses[lap]
    drift = se3.exp(np.array([0.0, 0.0, np.radians(3.0), 0.15, -0.1, 0.05]))
    new = keyframe("revisit", lap, 30, drift @ truth)
    verdict = place_recognition.verify(new, old, SETTINGS, np.random.default_rng(0))
    assert verdict.accepted, verdict.as_dict()
    true_relative = se3.inverse(old.pose) @ truth
    assert np.linalg.norm(verdict.relative[:3, 3] - true_relative[:3, 3]) < 0.005
    angle = se3.rotation_angle(true_relative[:3, :3].T @ verdict.relative[:3, :3])
    assert np.degrees(angle) < 0.2
    assert verdict.correction == pytest.approx(
        np.linalg.norm((se3.inverse(old.pose) @ new.pose)[:3, 3] - true_relative[:3, 3]), abs=0.01
    )


def test_identical_bays_fool_a_naive_matcher_but_not_the_verification():
    """The camera in front of the first bay and, 10 s later, of the second: appearance and
    sparse geometry agree (a naive matcher accepts), the dense photometric check does not.
    The plausibility gate is switched off here so that the dense checks alone decide."""
    first = int(TWINS_BAYS[0] / TWINS_SPEED * FRAME_RATE)
    second = int(TWINS_BAYS[1] / TWINS_SPEED * FRAME_RATE)
    old, new = keyframe("twins", first, 0), keyframe("twins", second, 30)
    rng = np.random.default_rng(0)
    assert place_recognition.naive_verify(new, old, SETTINGS, rng)
    no_gate = replace(SETTINGS, max_correction=100.0)
    verdict = place_recognition.verify(new, old, no_gate, rng)
    assert not verdict.accepted
    assert verdict.reason in ("dense", "photometric")
    # With the gate the loop is refused as well: it would move the camera 5 m.
    assert not place_recognition.verify(new, old, SETTINGS, rng).accepted


def test_a_walk_past_the_twins_accepts_no_loop():
    """Every keyframe of the `twins` walk (at its true poses) against every older one outside
    the recent window: candidates are verified, none is accepted."""
    s = scenario("twins")
    taken: list[keyframes.Keyframe] = []
    verdicts = []
    rng = np.random.default_rng(0)
    for frame in range(0, len(s), 6):
        pose = s.trajectory.poses[frame]
        if taken and not keyframes.is_new_keyframe(taken[-1].pose, pose, SETTINGS):
            continue
        new = keyframe("twins", frame, len(taken))
        new.travelled = TWINS_SPEED * frame / FRAME_RATE
        for candidate, _ in place_recognition.ranked_candidates(new, taken, SETTINGS):
            verdicts.append(place_recognition.verify(new, candidate, SETTINGS, rng))
        taken.append(new)
    assert len(taken) >= 12
    assert verdicts and not any(v.accepted for v in verdicts)
