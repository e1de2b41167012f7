# ruff: noqa: ANN001  (numba kernels: argument types come from the call)
"""The cuda backend's odometry stage (kintinuous_ref.odometry's names and signatures): the
CUDA systems - icp/cuda.py's and rgbd/cuda.py's per-frame problems, combined.py's joint problem,
the compiled Gauss-Newton step on the host, the model pyramid of device maps, the stale-stream
test on the device, FOVIS's host images downloaded once per frame and a dense estimate run
wholly on the device (frame_on_device.py) - and make_tracker, the reference's trackers over
them.

    tracker = load_backend("cuda").odometry.make_tracker("icp+rgbd", config, camera)
"""

from __future__ import annotations

import sys

import numpy as np
from numba import cuda

from kintinuous_fast.odometry import STAGE_NAMES
from kintinuous_fast.odometry.frame_on_device import estimate_on_device, repeats_kernel
from kintinuous_fast.odometry.sums.cuda import stage
from kintinuous_fast.preprocess.cuda import model_pyramid as model_pyramid
from kintinuous_fast.targets import is_device, to_host
from kintinuous_fast.targets.cuda import BLOCK_2D, grid_2d
from kintinuous_fast.targets.cuda_graphs import segment
from kintinuous_ref import odometry as _reference
from kintinuous_ref.camera import Intrinsics
from kintinuous_ref.config import Config
from kintinuous_ref.odometry import DenseTracker as DenseTracker
from kintinuous_ref.odometry import FovisTracker as FovisTracker
from kintinuous_ref.odometry import Systems, Tracker
from kintinuous_ref.odometry import TrackingResult as TrackingResult
from kintinuous_ref.odometry import stale_input as stale_input
from kintinuous_ref.preprocess import PreprocessedFrame, PyramidLevel
from kintinuous_ref.raycast import ModelPrediction

from .combined import CombinedProblem as CombinedProblem
from .icp.cuda import IcpProblem as IcpProblem
from .rgbd.cuda import RgbdProblem as RgbdProblem
from .solve import refine as refine

# __all__ (STAGE_NAMES): the reference's objects both targets export and this module's
# functions. Beside them, the members of Systems (kintinuous_ref.odometry.Systems) that
# kintinuous_ref.odometry imports rather than defines are imported here too: IcpProblem,
# RgbdProblem, CombinedProblem, model_pyramid and refine.
__all__ = STAGE_NAMES


def repeated_streams(
    previous: PreprocessedFrame | None, current: PreprocessedFrame
) -> tuple[bool, bool]:
    """kintinuous_ref.odometry.repeated_streams for frames on the device: the full-resolution
    images compared by one kernel, three flags downloaded (host frames: the reference's)."""
    if previous is None or not is_device(current.levels[0].depth):
        return _reference.repeated_streams(previous, current)
    before, now = previous.levels[0], current.levels[0]
    if tuple(before.depth.shape) != tuple(now.depth.shape):  # images of other sizes differ
        return False, False
    flags = cuda.to_device(np.zeros(3, dtype=np.int32))
    repeats_kernel[grid_2d(*now.depth.shape), BLOCK_2D](
        stage(before.depth), now.depth, stage(before.intensity), now.intensity, flags
    )
    any_depth, depth_differs, intensity_differs = to_host(flags)
    if not any_depth:  # a blind frame is never a repeat (the reference's rule)
        return False, False
    return not depth_differs, not intensity_differs


def is_repeated_frame(previous: PreprocessedFrame | None, current: PreprocessedFrame) -> bool:
    """True when both the depth and the colour image repeat the previous frame's."""
    return all(repeated_streams(previous, current))


def fovis_images(frame: PreprocessedFrame) -> PreprocessedFrame:
    """What FOVIS reads of a frame (every level's depth and intensity) as NumPy arrays: the frame
    itself when it is on the host, else a copy without the maps, gradients and colour."""
    if all(
        isinstance(image, np.ndarray)
        for level in frame.levels
        for image in (level.depth, level.intensity)
    ):
        return frame
    levels = [
        PyramidLevel(
            level.camera, to_host(level.depth), None, None, to_host(level.intensity), None, None
        )
        for level in frame.levels
    ]
    return PreprocessedFrame(colour=None, depth=levels[0].depth, levels=levels, colour_mask=None)


@segment
def estimate_dense(
    tracker: DenseTracker,
    previous: PreprocessedFrame,
    current: PreprocessedFrame,
    model: ModelPrediction | None,
    previous_pose: np.ndarray,
    start_pose: np.ndarray | None = None,
) -> tuple[np.ndarray, str]:
    """kintinuous_ref.odometry.estimate_dense: for frames on the device, every step there and one
    wait for the result (frame_on_device.py); host frames and a first frame, the reference's
    steps over this module's systems."""
    if previous is None or not is_device(current.levels[0].depth):
        return _reference.estimate_dense(
            tracker, previous, current, model, previous_pose, start_pose
        )
    return estimate_on_device(tracker, previous, current, model, previous_pose, start_pose)


def make_tracker(
    method: str, config: Config, camera: Intrinsics, systems: Systems | None = None
) -> Tracker:
    """kintinuous_ref.odometry.make_tracker (every method); `systems` None: this module, the
    CUDA kernels."""
    return _reference.make_tracker(method, config, camera, systems or sys.modules[__name__])
