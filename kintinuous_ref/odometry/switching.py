"""The paper's FOVIS switching strategy (section V-A).

ICP "slips" along corridors and other planar scenes; FOVIS, which tracks sparse image features,
rarely does. So whenever the two estimators disagree about how far the camera moved, the paper
trusts FOVIS:

    if | ||t_fovis||_2 - ||t_other||_2 | > mu   use T_fovis,   else use T_other,

with mu = 0.03 m found empirically (config.fovis.switch_threshold). Only the lengths of the
translations are compared, not their directions or the rotations. When FOVIS itself failed (too
few features or inliers) its increment means nothing and the other estimator's is used.
"""

from __future__ import annotations

import numpy as np

from kintinuous_ref.errors import ConfigError
from kintinuous_ref.se3 import PoseError

FOVIS = "fovis"
OTHER = "other"


def choose_increment(
    fovis_increment: np.ndarray, other_increment: np.ndarray, mu: float
) -> tuple[np.ndarray, str]:
    """Paper V-A: the FOVIS increment when | ||t_fovis|| - ||t_other|| | > mu, else the other one.

    Both increments are 4x4 relative motions (previous camera <- current camera). Returns the
    chosen matrix and which one it is, "fovis" or "other". At exactly mu the other estimator
    wins: the paper's test is a strict inequality.
    """
    if not mu >= 0:
        raise ConfigError(f"FOVIS switching threshold mu must be >= 0 m, got {mu}")
    _check_increment(fovis_increment, "FOVIS increment")
    _check_increment(other_increment, "other estimator's increment")
    disagreement = abs(
        float(np.linalg.norm(fovis_increment[:3, 3]))
        - float(np.linalg.norm(other_increment[:3, 3]))
    )
    if disagreement > mu:
        return fovis_increment, FOVIS
    return other_increment, OTHER


def choose_increment_or_fallback(
    fovis_increment: np.ndarray, fovis_ok: bool, other_increment: np.ndarray, mu: float
) -> tuple[np.ndarray, str]:
    """`choose_increment`, except that a failed FOVIS estimate always yields the other one."""
    if not fovis_ok:
        _check_increment(other_increment, "other estimator's increment")
        return other_increment, OTHER
    return choose_increment(fovis_increment, other_increment, mu)


def _check_increment(increment: np.ndarray, name: str) -> None:
    increment = np.asarray(increment)
    if increment.shape != (4, 4):
        raise PoseError(f"{name} must be a 4x4 matrix, got shape {increment.shape}")
    if not np.all(np.isfinite(increment)):
        raise PoseError(f"{name} contains NaN or infinity")
