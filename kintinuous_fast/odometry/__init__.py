"""Fast dense tracking (ICP, RGB-D, ICP+RGB-D) for the cpu and cuda backends.

The NumPy specification is ``kintinuous_ref.odometry``; this package mirrors it one estimator
per package or module, each with the reference module's public names and signatures:

    icp/        ops.py (one pair's maths, both targets), cpu.py (cpu_block.py: one block of
                pairs in vectorised loops), cuda.py; __init__: the host side of both
    rgbd/       ops.py, cpu.py, cuda.py, __init__ the same for the RGB-D odometry
    combined.py the joint system of both, compiled for the host (both targets)
    solve/      the Gauss-Newton step compiled for the host (__init__); cpu.py and cuda.py add
                each target's `accumulate`
    sums/       the normal equations as both targets sum them: the accumulated vector's slots
                and its unpacking (__init__), one row added (ops.py), the fixed-chunk sums of
                the CPU (cpu.py), the shared-memory block trees of CUDA (cuda.py)
    ops.py      the rigid transforms both estimators' ops use (each target compiles it and
                sums/ops.py once, in sums/cpu.py and sums/cuda.py)
    cpu.py      the backends' stage modules: this target's systems (the per-frame problems, the
    cuda.py     model pyramid, the solver, the stale-stream test, FOVIS's host images) and
                make_tracker, the reference's trackers over them

On the CPU, numba loops on all threads with fixed-chunk float64 sums (deterministic on any
thread count; lists in the reference's order). On CUDA, kernels following the paper's GPU
design (section IV-A): the interest-point list built per block in shared memory with one atomic
per block (Algorithm 1), the correspondence list and the intensity-difference sum with atomics
(Algorithm 2), J^T J / J^T r reduced by a shared-memory tree per block, the block partials
summed on the host in float64 and the 6x6 system solved there by Cholesky. CUDA lists come out
in atomic order (compare them as sets).

    tracker = load_backend("cpu").odometry.make_tracker("icp+rgbd", config, camera)
    result = tracker.track(previous_frame, current_frame, model_prediction, previous_pose)
"""

from __future__ import annotations

from typing import Any

from kintinuous_ref.camera import Intrinsics
from kintinuous_ref.errors import DatasetError

# kintinuous_ref.odometry's names that both stage modules (cpu.py, cuda.py) export as they are:
# the trackers, their results and seams (Systems), and the stale-stream rule.
TRACKER_NAMES = [
    "DenseTracker",
    "FovisTracker",
    "Systems",
    "Tracker",
    "TrackingResult",
    "stale_input",
]
# What each stage module exports: those, and the functions each target computes itself (on the
# cpu, the reference's own where the frames are NumPy arrays).
STAGE_NAMES = [
    *TRACKER_NAMES,
    "estimate_dense",
    "fovis_images",
    "is_repeated_frame",
    "make_tracker",
    "repeated_streams",
]


def check_map(name: str, array: Any, camera: Intrinsics) -> None:
    """A (h, w, 3) map of the camera's size, else a one-line DatasetError."""
    expected = (camera.height, camera.width, 3)
    if tuple(array.shape) != expected:
        raise DatasetError(f"{name} is {tuple(array.shape)}, expected {expected} from the camera")


def check_image(name: str, array: Any, shape: tuple[int, ...]) -> None:
    """An image of `shape`, else a one-line DatasetError."""
    if tuple(array.shape) != tuple(shape):
        raise DatasetError(f"{name} is {tuple(array.shape)}, expected {tuple(shape)}")
