# ruff: noqa: ANN001, ANN201  (numba kernels: argument types come from the call)
"""The device side of one dense estimate on the device (frame_on_device.py drives it): the
state vector's slots, and the kernels of the sequence (begin, repeats, mode, solve, finish)
beside the estimators' own (icp.cuda, rgbd.cuda). The solve kernel runs in one block: it adds
the blocks' partial sums in float64, forms the joint system, solves it as solve.solve does and
writes the new pose and the relative poses the next kernels read.
"""

from __future__ import annotations

import math

from numba import cuda, float64

from kintinuous_fast.odometry.solve import SOLVED
from kintinuous_fast.odometry.solve.ops import SCRATCH_MATRICES
from kintinuous_fast.odometry.solve.ops import build_ops as build_solve_ops
from kintinuous_fast.odometry.sums import NV, SLOT_B, SLOT_COST, SLOT_COUNT, SLOT_EXTRA
from kintinuous_fast.odometry.sums.cuda import (
    DEVICE,
    GATE_DONE_LEVEL,
    GATE_FAILED,
)
from kintinuous_fast.targets.cuda import kernel
from kintinuous_ref.odometry.combined import MIN_ICP_SCALE
from kintinuous_ref.vocabulary import ROBUST_WEIGHTINGS

# Slots of the state vector (float64): the gate (sums.cuda) first, then how the frame went, the
# inlier counts and, written last, the pose.
FAILED = GATE_FAILED
DONE_LEVEL = GATE_DONE_LEVEL
MODE = 2  # which system each step solves (JOINT, ICP_ONLY, RGBD_ONLY) or STALE
STATUS = 3  # solve's status codes (SOLVED, NOT_FINITE, ...) or TOO_FEW
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
TOO_FEW = 10  # a status beside solve's: fewer pairs than tracking.min_correspondences
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
SOLVE_THREADS = 64  # the solve kernel's block: a warp per estimator, a thread per slot of its sums

_ops = build_solve_ops(DEVICE)
# Module-level names: numba resolves the device functions as globals of the kernels below.
_scaled_solution = _ops.scaled_solution
_discounted_joint = _ops.discounted_joint
_increment = _ops.increment


# ----------------------------------------------------------------------------------------------
# Kernels


@kernel
def begin_kernel(state, flags, counts, tally):
    """The frame's state zeroed, no level done; one thread."""
    for s in range(state.shape[0]):
        state[s] = 0.0
    state[DONE_LEVEL] = -1.0
    for s in range(flags.shape[0]):
        flags[s] = 0
    for s in range(counts.shape[0]):
        counts[s] = 0
    tally[0] = 0.0
    tally[1] = 0.0


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
def _blocks_total(partials, slot):
    """The blocks' partials of `slot` added in block order. Eight loads go out before the first
    of their values is used: a GPU thread stalls on a load only where it reads the value, so
    the loads' latency (hundreds of cycles each, up to a thousand blocks) overlaps eightfold,
    while the additions keep their order."""
    blocks = partials.shape[0]
    total = 0.0
    k = 0
    while k + 8 <= blocks:
        v0, v1 = partials[k, slot], partials[k + 1, slot]
        v2, v3 = partials[k + 2, slot], partials[k + 3, slot]
        v4, v5 = partials[k + 4, slot], partials[k + 5, slot]
        v6, v7 = partials[k + 6, slot], partials[k + 7, slot]
        total = total + v0 + v1 + v2 + v3 + v4 + v5 + v6 + v7  # left to right: block order
        k += 8
    while k < blocks:
        total += partials[k, slot]
        k += 1
    return total


@cuda.jit(device=True)
def _add_partials(icp_partials, rgbd_partials, sums):
    """sums[0] = ICP's block partials added, sums[1] = RGB-D's: the block's first warp adds
    ICP's, its second RGB-D's, one slot per thread (SOLVE_THREADS)."""
    warp, slot = cuda.threadIdx.x // 32, cuda.threadIdx.x % 32
    if slot < NV and warp == 0:
        sums[0, slot] = _blocks_total(icp_partials, slot)
    elif slot < NV and warp == 1:
        sums[1, slot] = _blocks_total(rgbd_partials, slot)


@cuda.jit(device=True)
def _unpack(sums, row, a, b):
    """A (upper triangle mirrored) and b of the summed vector sums[row] (sums.unpack)."""
    slot = 0
    for i in range(6):
        for j in range(i, 6):
            a[i, j] = sums[row, slot]
            a[j, i] = sums[row, slot]
            slot += 1
        b[i] = sums[row, SLOT_B + i]


@cuda.jit(device=True)
def _scale_of(sums, row, floor):
    """combined.icp_scale / rgbd_scale: the RMS residual of a term, at least `floor`, 1 when
    it has no rows."""
    count = sums[row, SLOT_COUNT]
    if count == 0:
        return 1.0
    return max(math.sqrt(sums[row, SLOT_COST] / count), floor)


@cuda.jit(device=True)
def _weights(sums, weighting, rgbd_weight, icp_code_scale):
    """(ICP's A scale, ICP's b scale, RGB-D's scale) of combined.joint_system's weightings;
    DISCOUNTED also shrinks ICP's weak directions (_discounted_joint)."""
    if weighting == PAPER_METRES:
        return 1.0, 1.0, rgbd_weight
    if weighting == ORIGINAL_CODE:
        return icp_code_scale * icp_code_scale, icp_code_scale, 1.0
    icp_weight = 1.0 / _scale_of(sums, 0, MIN_ICP_SCALE) ** 2
    if weighting == INFORMATION:
        return icp_weight, icp_weight, rgbd_weight / _scale_of(sums, 1, 1e-6) ** 2
    return icp_weight, icp_weight, rgbd_weight


@cuda.jit(device=True)
def _system(sums, mode, settings, pose, a, b, work, scratch):
    """The step's normal equations into (a, b) and their row count: ICP's, RGB-D's or the
    joint system of the two (combined.joint_system with settings' weighting)."""
    icp_a, icp_b, rgbd_a, rgbd_b = work[0], work[1, 0], work[2], work[1, 1]
    _unpack(sums, 0, icp_a, icp_b)
    _unpack(sums, 1, rgbd_a, rgbd_b)
    if mode == ICP_ONLY:
        scale_a, scale_b, rgbd_scale = 1.0, 1.0, 0.0
    elif mode == RGBD_ONLY:
        scale_a, scale_b, rgbd_scale = 0.0, 0.0, 1.0
    else:
        _, _, weighting, rgbd_weight, code_scale, threshold = settings
        scale_a, scale_b, rgbd_scale = _weights(sums, weighting, rgbd_weight, code_scale)
        if weighting == DISCOUNTED:
            count = sums[0, SLOT_COUNT]
            _discounted_joint(
                icp_a, icp_b, count, scale_a, rgbd_a, rgbd_b, rgbd_scale,
                pose[0, 3], pose[1, 3], pose[2, 3], threshold, a, b, scratch,
            )  # fmt: skip
            return sums[0, SLOT_COUNT] + sums[1, SLOT_COUNT]
    for i in range(6):
        for j in range(6):
            a[i, j] = icp_a[i, j] * scale_a + rgbd_a[i, j] * rgbd_scale
        b[i] = icp_b[i] * scale_b + rgbd_b[i] * rgbd_scale
    count = 0.0
    if mode != RGBD_ONLY:
        count += sums[0, SLOT_COUNT]
    if mode != ICP_ONLY:
        count += sums[1, SLOT_COUNT]
    return count


@cuda.jit(device=True)
def _fail(state, status, level, condition, count):
    state[FAILED] = 1.0
    state[STATUS] = status
    state[FAIL_LEVEL] = level
    state[CONDITION] = condition
    state[FAIL_COUNT] = count


@cuda.jit(device=True)
def _update_poses(poses, updated):
    """The new estimate where the next kernels read it: as itself (ICP's and RGB-D's slot), in
    the model camera (ICP) and relative to the previous camera (RGB-D)."""
    for i in range(4):
        for j in range(4):
            poses[0, i, j] = updated[i, j]
            poses[3, i, j] = updated[i, j]
    for i in range(4):
        for j in range(4):
            to_model = 0.0
            relative = 0.0
            for k in range(4):
                to_model += poses[MODEL_INVERSE, i, k] * updated[k, j]
                relative += poses[PREVIOUS_INVERSE, i, k] * updated[k, j]
            poses[1, i, j] = to_model
            poses[2, i, j] = relative


@kernel
def solve_kernel(icp_partials, rgbd_partials, tally, state, poses, settings, level):
    """One Gauss-Newton step (solve.refine's loop body) in one block: the partial sums added,
    the system formed and solved, the increment applied; the gate closed on failure or
    convergence. `settings` = (min_count, converged, weighting, rgbd_weight, original code's
    ICP scale, degeneracy threshold)."""
    sums = cuda.shared.array((2, NV), float64)
    if state[FAILED] != 0.0 or state[DONE_LEVEL] == level:
        return
    _add_partials(icp_partials, rgbd_partials, sums)
    cuda.syncthreads()
    if cuda.threadIdx.x != 0:
        return
    a = cuda.local.array((6, 6), float64)
    b = cuda.local.array(6, float64)
    xi = cuda.local.array(6, float64)
    updated = cuda.local.array((4, 4), float64)
    work = cuda.local.array((3, 6, 6), float64)
    scratch = cuda.local.array((SCRATCH_MATRICES, 6, 6), float64)
    min_count, converged = settings[0], settings[1]
    count = _system(sums, int(state[MODE]), settings, poses[0], a, b, work, scratch)
    tally[0] = 0.0  # the next step's Algorithm 2 lists from zero
    tally[1] = 0.0
    if count < min_count:
        _fail(state, TOO_FEW, level, 0.0, count)
        return
    status, condition = _scaled_solution(a, b, xi, scratch)
    if status != SOLVED:
        _fail(state, status, level, condition, count)
        return
    _increment(xi, poses[0], updated, scratch)
    _update_poses(poses, updated)
    norm = math.sqrt(xi[0] ** 2 + xi[1] ** 2 + xi[2] ** 2 + xi[3] ** 2 + xi[4] ** 2 + xi[5] ** 2)
    if norm < converged:
        state[DONE_LEVEL] = level


@kernel
def finish_kernel(icp_partials, tally, counts, state, poses, finest):
    """The record: the inlier check's counts at the finest level and the estimate; one thread."""
    state[ICP_PAIRS] = _blocks_total(icp_partials, SLOT_COUNT)
    state[ICP_VALID] = _blocks_total(icp_partials, SLOT_EXTRA)
    state[RGBD_PAIRS] = tally[0]
    state[RGBD_POINTS] = counts[finest]
    for i in range(4):
        for j in range(4):
            state[POSE + 4 * i + j] = poses[0, i, j]
