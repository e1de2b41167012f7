"""The cpu backend's odometry stage (kintinuous_ref.odometry's names and signatures): the CPU's
systems - icp/cpu.py's and rgbd/cpu.py's per-frame problems, combined.py's joint problem, the
compiled Gauss-Newton step, the reference's model pyramid, stale-stream test and FOVIS images
(the frames are NumPy arrays here) - and make_tracker, the reference's trackers over them.

    tracker = select_backend("cpu").odometry.make_tracker("icp+rgbd", config, camera)
"""

from __future__ import annotations

import sys

from kintinuous_ref import odometry as _reference
from kintinuous_ref.camera import Intrinsics
from kintinuous_ref.config import Config
from kintinuous_ref.odometry import (
    DenseTracker,
    FovisTracker,
    Systems,
    Tracker,
    TrackingResult,
    fovis_images,
    is_repeated_frame,
    repeated_streams,
    stale_input,
)
from kintinuous_ref.preprocess import model_pyramid as model_pyramid

from .combined import CombinedProblem as CombinedProblem
from .icp.cpu import IcpProblem as IcpProblem
from .rgbd.cpu import RgbdProblem as RgbdProblem
from .solve import refine as refine

# Beside __all__, the members of Systems (kintinuous_ref.odometry.Systems) that
# kintinuous_ref.odometry imports rather than defines are imported here too: IcpProblem,
# RgbdProblem, CombinedProblem, model_pyramid and refine.
__all__ = [
    "DenseTracker",
    "FovisTracker",
    "Systems",
    "Tracker",
    "TrackingResult",
    "fovis_images",
    "is_repeated_frame",
    "make_tracker",
    "repeated_streams",
    "stale_input",
]


def make_tracker(
    method: str, config: Config, camera: Intrinsics, systems: Systems | None = None
) -> Tracker:
    """kintinuous_ref.odometry.make_tracker (every method); `systems` None: this module, the CPU
    loops."""
    return _reference.make_tracker(method, config, camera, systems or sys.modules[__name__])
