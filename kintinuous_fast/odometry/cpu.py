"""The cpu backend's odometry stage (kintinuous_ref.odometry's names and signatures): the CPU's
systems - icp/cpu.py's and rgbd/cpu.py's per-frame problems, combined.py's joint problem, the
compiled Gauss-Newton step, the reference's model pyramid, stale-stream test, FOVIS images and
steps of one dense estimate (the frames are NumPy arrays here) - and make_tracker, the
reference's trackers over them.

    tracker = load_backend("cpu").odometry.make_tracker("icp+rgbd", config, camera)
"""

from __future__ import annotations

import sys
from collections.abc import Callable, Sequence

import numpy as np

from kintinuous_fast.odometry import STAGE_NAMES
from kintinuous_ref import odometry as _reference
from kintinuous_ref.camera import Intrinsics
from kintinuous_ref.config import Config, TrackingConfig
from kintinuous_ref.odometry import DenseTracker as DenseTracker
from kintinuous_ref.odometry import FovisTracker as FovisTracker
from kintinuous_ref.odometry import Systems, Tracker
from kintinuous_ref.odometry import TrackingResult as TrackingResult
from kintinuous_ref.odometry import estimate_dense as estimate_dense
from kintinuous_ref.odometry import fovis_images as fovis_images
from kintinuous_ref.odometry import is_repeated_frame as is_repeated_frame
from kintinuous_ref.odometry import repeated_streams as repeated_streams
from kintinuous_ref.odometry import solve as reference_solve
from kintinuous_ref.odometry import stale_input as stale_input
from kintinuous_ref.preprocess import model_pyramid as model_pyramid

from .combined import CombinedProblem as CombinedProblem
from .icp.cpu import IcpProblem as IcpProblem
from .icp.cpu_joint import JOINT_STEP
from .rgbd.cpu import RgbdProblem as RgbdProblem

# __all__ (STAGE_NAMES): the reference's objects both targets export and this module's
# functions. Beside them, the members of Systems (kintinuous_ref.odometry.Systems) that
# kintinuous_ref.odometry imports rather than defines are imported here too: IcpProblem,
# RgbdProblem, CombinedProblem and model_pyramid; `refine` is this module's.
__all__ = STAGE_NAMES


def refine(
    pose: np.ndarray,
    system_at: Callable[[int, np.ndarray], reference_solve.LinearSystem],
    iterations: Sequence[int],
    min_count: int = 6,
    converged: float = TrackingConfig.converged_step,
    step: tuple[Callable, Callable] | None = None,
) -> tuple[np.ndarray, str]:
    """odometry.solve.refine (the reference's coarse-to-fine loop and compiled step) with the
    joint loop's step (icp/cpu_joint.JOINT_STEP): where the system came from the joint loop, its
    step was taken in the call that summed it, one compiled call an iteration instead of three;
    the same functions on the same values, so the same poses."""
    return reference_solve.refine(
        pose, system_at, iterations, min_count, converged, step or JOINT_STEP
    )


def make_tracker(
    method: str, config: Config, camera: Intrinsics, systems: Systems | None = None
) -> Tracker:
    """kintinuous_ref.odometry.make_tracker (every method); `systems` None: this module, the CPU
    loops."""
    return _reference.make_tracker(method, config, camera, systems or sys.modules[__name__])
