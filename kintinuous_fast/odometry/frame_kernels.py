# ruff: noqa: ANN001, ANN201  (numba kernels: argument types come from the call)
"""The device side of one dense estimate on the device (frame_on_device.py drives it): the
state vector's slots, and the kernels of the sequence (begin, repeats, mode, finish) beside the
estimators' own (icp.cuda, rgbd.cuda) and the solve kernel's (frame_solve.py).
"""

from __future__ import annotations

from numba import cuda

from kintinuous_fast.odometry.solve import TOO_FEW as TOO_FEW  # a value of the STATUS slot
from kintinuous_fast.odometry.sums import SLOT_COUNT, SLOT_EXTRA
from kintinuous_fast.odometry.sums.cuda import GATE_DONE_LEVEL, GATE_FAILED
from kintinuous_fast.targets.cuda import kernel
from kintinuous_ref.vocabulary import ROBUST_WEIGHTINGS

# Slots of the state vector (float64): the gate (sums.cuda) first, then how the frame went, the
# inlier counts and, written last, the pose.
FAILED = GATE_FAILED
DONE_LEVEL = GATE_DONE_LEVEL
MODE = 2  # which system each step solves (JOINT, ICP_ONLY, RGBD_ONLY) or STALE
STATUS = 3  # solve's status codes (SOLVED, NOT_FINITE, ..., TOO_FEW)
FAIL_LEVEL = 4
CONDITION = 5
FAIL_COUNT = 6
DEPTH_SEEN = 7  # the stale-stream test's flags (kintinuous_ref.odometry.repeated_streams)
DEPTH_DIFFERS = 8
INTENSITY_DIFFERS = 9
ICP_PAIRS = 10  # at the finest level, at the estimate: the inlier check's counts
ICP_VALID = 11
RGBD_PAIRS = 12
RGBD_POINTS = 13
POSE = 16  # 16 slots, row-major
STATE_SIZE = 32

JOINT, ICP_ONLY, RGBD_ONLY, STALE = range(4)
# The weightings of combined.joint_system as the solve kernel takes them.
DISCOUNTED, PAPER, PAPER_METRES, INFORMATION, ORIGINAL_CODE = range(5)
WEIGHTING_CODES = {
    "degeneracy-aware": DISCOUNTED,
    **dict.fromkeys(ROBUST_WEIGHTINGS, DISCOUNTED),
    "paper": PAPER,
    "paper-metres": PAPER_METRES,
    "information": INFORMATION,
    "original-code": ORIGINAL_CODE,
    "elasticfusion": ORIGINAL_CODE,
}
METHOD_MODES = {"icp+rgbd": JOINT, "icp": ICP_ONLY, "rgbd": RGBD_ONLY}
# Slots of the device array of poses (4x4 each): ICP reads POSES_ICP (the estimate, current
# camera to model camera), RGB-D POSES_RGBD (relative, estimate, previous) as the host-driven
# kernels take them; the last two are the frame's constants the solve kernel multiplies by.
POSES_ICP = slice(0, 2)
POSES_RGBD = slice(2, 5)
PREVIOUS_INVERSE, MODEL_INVERSE = 5, 6


# ----------------------------------------------------------------------------------------------
# Kernels


@kernel
def begin_kernel(state, flags, counts, tally, basis):
    """The frame's state zeroed, no level done, the solve kernel's eigenvector basis the
    identity (so that a frame's steps start from the same basis however long the run); one
    thread."""
    for s in range(state.shape[0]):
        state[s] = 0.0
    state[DONE_LEVEL] = -1.0
    for s in range(flags.shape[0]):
        flags[s] = 0
    for s in range(counts.shape[0]):
        counts[s] = 0
    tally[0] = 0.0
    tally[1] = 0.0
    for i in range(6):
        for j in range(6):
            basis[i, j] = 1.0 if i == j else 0.0


@kernel
def repeats_kernel(depth_before, depth_now, intensity_before, intensity_now, flags):
    """flags[0] = 1 if any depth now, [1] = 1 if any depth differs, [2] = 1 if any intensity
    differs (every writer writes the same 1: no atomics needed). != is True for NaN, as
    np.array_equal's test is False."""
    u, v = cuda.grid(2)
    if v < depth_now.shape[0] and u < depth_now.shape[1]:
        if depth_now[v, u] > 0:
            flags[0] = 1
        if depth_now[v, u] != depth_before[v, u]:
            flags[1] = 1
        if intensity_now[v, u] != intensity_before[v, u]:
            flags[2] = 1


@kernel
def mode_kernel(flags, state, method):
    """estimate_dense's stale-stream rule (stale_input): the frame fails when the method has
    no fresh image, and ICP+RGB-D solves for the fresh stream alone when one repeats; one
    thread. `method` = METHOD_MODES of the tracker."""
    state[DEPTH_SEEN] = flags[0]
    state[DEPTH_DIFFERS] = flags[1]
    state[INTENSITY_DIFFERS] = flags[2]
    seen = flags[0] != 0  # a blind frame is never a repeat
    depth_repeated = seen and flags[1] == 0
    colour_repeated = seen and flags[2] == 0
    mode = method
    if method == JOINT and colour_repeated:
        mode = ICP_ONLY
    elif method == JOINT and depth_repeated:
        mode = RGBD_ONLY
    stale = depth_repeated and colour_repeated
    stale = stale or (colour_repeated and method == RGBD_ONLY)
    stale = stale or (depth_repeated and method == ICP_ONLY)
    state[MODE] = STALE if stale else mode
    if stale:
        state[FAILED] = 1.0


@cuda.jit(device=True)
def blocks_total(partials, slot, start, stop):
    """partials[start:stop, slot] added in block order. Eight loads go out before the first of
    their values is used: a GPU thread stalls on a load only where it reads the value, so the
    loads' latency (hundreds of cycles each) overlaps eightfold, while the additions keep their
    order."""
    total = 0.0
    k = start
    while k + 8 <= stop:
        v0, v1 = partials[k, slot], partials[k + 1, slot]
        v2, v3 = partials[k + 2, slot], partials[k + 3, slot]
        v4, v5 = partials[k + 4, slot], partials[k + 5, slot]
        v6, v7 = partials[k + 6, slot], partials[k + 7, slot]
        total = total + v0 + v1 + v2 + v3 + v4 + v5 + v6 + v7  # left to right: block order
        k += 8
    while k < stop:
        total += partials[k, slot]
        k += 1
    return total


@kernel
def finish_kernel(icp_partials, tally, counts, state, poses, finest):
    """The record: the inlier check's counts at the finest level and the estimate; one thread."""
    blocks = icp_partials.shape[0]
    state[ICP_PAIRS] = blocks_total(icp_partials, SLOT_COUNT, 0, blocks)
    state[ICP_VALID] = blocks_total(icp_partials, SLOT_EXTRA, 0, blocks)
    state[RGBD_PAIRS] = tally[0]
    state[RGBD_POINTS] = counts[finest]
    for i in range(4):
        for j in range(4):
            state[POSE + 4 * i + j] = poses[0, i, j]
