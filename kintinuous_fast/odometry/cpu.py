"""The cpu backend's odometry stage (kintinuous_ref.odometry's names and signatures): the CPU's
systems - icp/cpu.py's and rgbd/cpu.py's per-frame problems, combined.py's joint problem, the
compiled Gauss-Newton step, the stale-stream test compiled, the reference's model pyramid, FOVIS
images and steps of one dense estimate (the frames are NumPy arrays here) - and make_tracker, the
reference's trackers over them.

    tracker = load_backend("cpu").odometry.make_tracker("icp+rgbd", config, camera)
"""

from __future__ import annotations

import sys

import numba
import numpy as np

from kintinuous_fast.odometry import STAGE_NAMES
from kintinuous_ref import odometry as _reference
from kintinuous_ref.camera import Intrinsics
from kintinuous_ref.config import Config
from kintinuous_ref.odometry import DenseTracker as DenseTracker
from kintinuous_ref.odometry import FovisTracker as FovisTracker
from kintinuous_ref.odometry import Systems, Tracker
from kintinuous_ref.odometry import TrackingResult as TrackingResult
from kintinuous_ref.odometry import estimate_dense as estimate_dense
from kintinuous_ref.odometry import fovis_images as fovis_images
from kintinuous_ref.odometry import is_repeated_frame as is_repeated_frame
from kintinuous_ref.odometry import stale_input as stale_input
from kintinuous_ref.preprocess import PreprocessedFrame
from kintinuous_ref.preprocess import model_pyramid as model_pyramid

from .combined import CombinedProblem as CombinedProblem
from .icp.cpu import IcpProblem as IcpProblem
from .rgbd.cpu import RgbdProblem as RgbdProblem
from .solve import refine as refine

# __all__ (STAGE_NAMES): the reference's objects both targets export and this module's
# functions. Beside them, the members of Systems (kintinuous_ref.odometry.Systems) that
# kintinuous_ref.odometry imports rather than defines are imported here too: IcpProblem,
# RgbdProblem, CombinedProblem, model_pyramid and refine.
__all__ = STAGE_NAMES


@numba.njit(cache=True)
def _any_positive(image: np.ndarray) -> bool:
    """np.any(image > 0) of a 2-d image, stopping at the first positive pixel."""
    for v in range(image.shape[0]):
        for u in range(image.shape[1]):
            if image[v, u] > 0:
                return True
    return False


@numba.njit(cache=True)
def _equal(a: np.ndarray, b: np.ndarray) -> bool:
    """np.array_equal of two 2-d images, stopping at the first pixel that differs (!= is True
    for NaN, as array_equal's test is False)."""
    if a.shape != b.shape:
        return False
    for v in range(a.shape[0]):
        for u in range(a.shape[1]):
            if a[v, u] != b[v, u]:
                return False
    return True


def repeated_streams(
    previous: PreprocessedFrame | None, current: PreprocessedFrame
) -> tuple[bool, bool]:
    """kintinuous_ref.odometry.repeated_streams compiled: each comparison stops at the first
    pixel that settles it, where NumPy's compares and reduces whole images (about 0.5 ms a
    640x480 frame), and a fresh image differs within its first row."""
    if previous is None:
        return False, False
    before, now = previous.levels[0], current.levels[0]
    if not _any_positive(now.depth):
        return False, False
    return _equal(before.depth, now.depth), _equal(before.intensity, now.intensity)


def make_tracker(
    method: str, config: Config, camera: Intrinsics, systems: Systems | None = None
) -> Tracker:
    """kintinuous_ref.odometry.make_tracker (every method); `systems` None: this module, the CPU
    loops."""
    return _reference.make_tracker(method, config, camera, systems or sys.modules[__name__])
