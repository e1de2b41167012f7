"""The paper's FOVIS switching strategy (section V-A).

ICP "slips" along corridors and other planar scenes; FOVIS, which tracks sparse image features,
rarely does. So whenever the two estimators disagree about how far the camera moved, the paper
trusts FOVIS:

    if | ||t_fovis||_2 - ||t_other||_2 | > mu   use T_fovis,   else use T_other,

with mu = 0.03 m found empirically (config.fovis.switch_threshold). Only the lengths of the
translations are compared, not their directions or the rotations. The rule "vector"
(config.fovis.switch_rule) compares the translations themselves, ||t_fovis - t_other||_2 > mu,
and so also catches an estimator that moved as far as FOVIS but the wrong way, which on large
motions the length rule keeps (docs/odometry.md). When FOVIS itself failed (too few features or
inliers) its increment means nothing and the other estimator's is used.

The paper does not say where the other estimator starts. With config.fovis.dense_from_fovis it
starts from FOVIS's increment (odometry.FovisTracker.dense_start), so that the rule compares a
dense refinement of FOVIS's motion with FOVIS's own; otherwise from the previous pose, the dense
trackers' initial estimate, which over large motions lets it converge to another basin.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from kintinuous_ref.errors import ConfigError
from kintinuous_ref.se3 import PoseError
from kintinuous_ref.vocabulary import SWITCH_RULES

FOVIS = "fovis"
OTHER = "other"


@dataclass(frozen=True)
class SwitchDecision:
    """One frame of fovis/X: both estimators' increments (previous camera <- current camera),
    where the dense one started and which the rule chose."""

    fovis_increment: np.ndarray | None  # None: FOVIS failed
    dense_increment: np.ndarray | None  # None: the dense estimator failed
    dense_start: np.ndarray  # the increment its Gauss-Newton started from (identity: none)
    chosen: str = ""  # FOVIS or OTHER; '' when both failed

    def chose(self, chosen: str) -> SwitchDecision:
        """This decision with `chosen` recorded."""
        return replace(self, chosen=chosen)


def choose_increment(
    fovis_increment: np.ndarray, other_increment: np.ndarray, mu: float, rule: str = "length"
) -> tuple[np.ndarray, str]:
    """Paper V-A: the FOVIS increment when | ||t_fovis|| - ||t_other|| | > mu ("length"; with
    "vector": ||t_fovis - t_other|| > mu), else the other one.

    Both increments are 4x4 relative motions (previous camera <- current camera). Returns the
    chosen matrix and which one it is, "fovis" or "other". At exactly mu the other estimator
    wins: the paper's test is a strict inequality.
    """
    if not mu >= 0:
        raise ConfigError(f"FOVIS switching threshold mu must be >= 0 m, got {mu}")
    _check_increment(fovis_increment, "FOVIS increment")
    _check_increment(other_increment, "other estimator's increment")
    if rule not in SWITCH_RULES:
        raise ConfigError(f"FOVIS switching rule must be one of {SWITCH_RULES}, got {rule!r}")
    t_fovis, t_other = fovis_increment[:3, 3], other_increment[:3, 3]
    if rule == "vector":
        disagreement = float(np.linalg.norm(t_fovis - t_other))
    else:  # eq. of section V-A
        disagreement = abs(float(np.linalg.norm(t_fovis)) - float(np.linalg.norm(t_other)))
    if disagreement > mu:
        return fovis_increment, FOVIS
    return other_increment, OTHER


def choose_increment_or_fallback(
    fovis_increment: np.ndarray,
    fovis_ok: bool,
    other_increment: np.ndarray,
    mu: float,
    rule: str = "length",
) -> tuple[np.ndarray, str]:
    """`choose_increment`, except that a failed FOVIS estimate always yields the other one."""
    if not fovis_ok:
        _check_increment(other_increment, "other estimator's increment")
        return other_increment, OTHER
    return choose_increment(fovis_increment, other_increment, mu, rule)


def _check_increment(increment: np.ndarray, name: str) -> None:
    increment = np.asarray(increment)
    if increment.shape != (4, 4):
        raise PoseError(f"{name} must be a 4x4 matrix, got shape {increment.shape}")
    if not np.all(np.isfinite(increment)):
        raise PoseError(f"{name} contains NaN or infinity")
