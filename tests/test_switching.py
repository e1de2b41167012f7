"""The paper's switching rule (V-A) on hand-made increments.

Translations are chosen as exact binary fractions (0.5, 0.25, ...) so that the disagreement
| ||t_fovis|| - ||t_other|| | is computed without rounding and the boundary case is truly at mu.
"""

import numpy as np
import pytest

from kintinuous_ref import se3
from kintinuous_ref.errors import ConfigError
from kintinuous_ref.odometry.switching import choose_increment, choose_increment_or_fallback

MU = 0.03  # the paper's value


def increment(translation, rotation=(0.0, 0.0, 0.0)):
    return se3.exp(np.array([*rotation, *translation], dtype=float))


def test_large_disagreement_uses_fovis():
    fovis = increment([0.10, 0.0, 0.0])
    other = increment([0.05, 0.0, 0.0])  # 5 cm apart in length > 3 cm
    chosen, used = choose_increment(fovis, other, MU)
    assert used == "fovis"
    assert chosen is fovis


def test_large_disagreement_either_way_uses_fovis():
    """ICP slipping can also under-estimate the motion: the test is on the absolute value."""
    fovis = increment([0.0, 0.0, 0.01])
    other = increment([0.0, 0.0, 0.08])
    assert choose_increment(fovis, other, MU)[1] == "fovis"


def test_small_disagreement_uses_the_other_estimator():
    fovis = increment([0.02, 0.0, 0.0], rotation=(0.0, 0.1, 0.0))
    other = increment([0.0, 0.03, 0.0])  # 1 cm apart in length < 3 cm
    chosen, used = choose_increment(fovis, other, MU)
    assert used == "other"
    assert chosen is other


def test_equal_lengths_in_different_directions_use_the_other_estimator():
    """Only the lengths are compared: opposite directions of equal length count as agreement."""
    fovis = increment([0.3, 0.4, 0.0])
    other = increment([0.0, 0.0, -0.5])
    assert choose_increment(fovis, other, MU)[1] == "other"


def test_rotations_are_not_compared():
    fovis = increment([0.05, 0.0, 0.0], rotation=(0.0, 0.0, 0.0))
    other = increment([0.05, 0.0, 0.0], rotation=(0.0, 0.5, 0.0))
    assert choose_increment(fovis, other, MU)[1] == "other"


def test_boundary_is_strict():
    """Disagreement exactly mu: the paper's '>' keeps the other estimator; a hair less: FOVIS."""
    fovis = increment([0.5, 0.0, 0.0])
    other = increment([0.0, 0.25, 0.0])
    assert choose_increment(fovis, other, 0.25)[1] == "other"
    assert choose_increment(fovis, other, np.nextafter(0.25, 0.0))[1] == "fovis"


def test_failed_fovis_falls_back_to_the_other_estimator():
    fovis = increment([0.5, 0.0, 0.0])
    other = increment([0.0, 0.0, 0.0])
    chosen, used = choose_increment_or_fallback(fovis, False, other, MU)
    assert used == "other" and chosen is other
    # With FOVIS ok the same pair switches to FOVIS.
    assert choose_increment_or_fallback(fovis, True, other, MU)[1] == "fovis"


def test_bad_inputs_are_reported():
    good = np.eye(4)
    with pytest.raises(ConfigError, match="mu must be >= 0"):
        choose_increment(good, good, -0.01)
    with pytest.raises(se3.PoseError, match="FOVIS increment must be a 4x4"):
        choose_increment(np.eye(3), good, MU)
    bad = np.eye(4)
    bad[0, 3] = np.nan
    with pytest.raises(se3.PoseError, match="other estimator's increment contains NaN"):
        choose_increment(good, bad, MU)


def test_vector_rule_sees_a_motion_of_equal_length_the_other_way():
    # both 10 cm long, in opposite directions: no disagreement in length, 20 cm as vectors
    fovis, other = np.eye(4), np.eye(4)
    fovis[:3, 3] = [0.1, 0.0, 0.0]
    other[:3, 3] = [-0.1, 0.0, 0.0]
    assert choose_increment(fovis, other, MU)[1] == "other"
    assert choose_increment(fovis, other, MU, "vector")[1] == "fovis"
    assert choose_increment(fovis, other, 0.2, "vector")[1] == "other"  # strict, as the paper's
    assert choose_increment(fovis, other, np.nextafter(0.2, 0.0), "vector")[1] == "fovis"
    with pytest.raises(ConfigError):
        choose_increment(fovis, other, MU, "angle")


def test_the_rule_is_a_checked_setting():
    from kintinuous_ref.config import Config, with_overrides

    assert Config().fovis.switch_rule == "length"  # the paper's
    assert with_overrides(Config(), {"fovis.switch_rule": "vector"}).fovis.switch_rule == "vector"
    with pytest.raises(ConfigError, match="switch_rule"):
        with_overrides(Config(), {"fovis.switch_rule": "angle"})


def test_the_dense_start_is_a_checked_setting():
    from kintinuous_ref.config import Config, with_overrides

    assert Config().fovis.dense_from_fovis is True  # measured: docs/odometry.md
    assert (
        with_overrides(Config(), {"fovis.dense_from_fovis": False}).fovis.dense_from_fovis is False
    )
    with pytest.raises(ConfigError, match="dense_from_fovis"):
        with_overrides(Config(), {"fovis.dense_from_fovis": "fovis"})


def test_the_dense_half_starts_from_fovis_else_from_the_last_good_increment():
    from kintinuous_ref.camera import Intrinsics
    from kintinuous_ref.config import Config, with_overrides
    from kintinuous_ref.odometry import FovisTracker

    camera = Intrinsics(525.0, 525.0, 319.5, 239.5, 640, 480)
    fovis_step, last_step = np.eye(4), np.eye(4)
    fovis_step[:3, 3] = (0.2, 0.0, 0.05)
    last_step[:3, 3] = (0.15, 0.01, 0.0)
    tracker = FovisTracker("fovis/icp+rgbd", Config(), camera)
    first_pose = np.eye(4)
    tracker.recovery.success(first_pose @ last_step, first_pose, "icp+rgbd")  # a good frame
    assert np.array_equal(tracker.dense_start(fovis_step, True), fovis_step)
    np.testing.assert_allclose(tracker.dense_start(fovis_step, False), last_step, atol=1e-15)
    tracker.recovery.failure(first_pose, "lost")  # a failed frame: no motion to carry on
    assert np.array_equal(tracker.dense_start(fovis_step, False), np.eye(4))
    paper = FovisTracker(
        "fovis/icp+rgbd", with_overrides(Config(), {"fovis.dense_from_fovis": False}), camera
    )
    assert paper.dense_start(fovis_step, True) is None  # the previous pose, as the paper's
