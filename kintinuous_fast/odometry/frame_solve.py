# ruff: noqa: ANN001, ANN201  (numba kernels: argument types come from the call)
"""The solve kernel of the frame on the device (frame_on_device.py): one Gauss-Newton step
(solve.refine's loop body) in one CUDA block. It adds the blocks' partial sums, forms the joint
system (combined.joint_system, every weighting), solves it as solve.solve does, applies the
increment (eq. 4) and writes the new pose with the relative poses the next kernels read.

The block shares the work. Its warps add the partial sums in parallel: each estimator's blocks
are cut into one contiguous range per pair of warps, a warp adds its range in block order (a
thread per slot) and the ranges are then added in order. The 6x6 algebra (solve/ops.py) runs
with the block's threads as its lanes, a thread per matrix element, and `cuda.syncthreads` as
its barrier: the eigenproblems in Jacobi's parallel ordering, the products an element per
thread. Thread 0 alone does what is scalar: the checks, Cholesky, the increment and the poses.
A single thread used to do all of it, each float64 operation waiting for the one before while
the rest of the GPU waited for the step.

Every device function that meets a barrier is compiled from this module or from ops.py (whose
functions take the barrier from here): numba's simulator swaps a module's `cuda` for the
launch's while a device function of another module runs, and the first thread to leave swaps
it back under the others.
"""

from __future__ import annotations

import math

from numba import cuda, float64

from kintinuous_fast.odometry.frame_kernels import (
    CONDITION,
    DISCOUNTED,
    DONE_LEVEL,
    FAIL_COUNT,
    FAIL_LEVEL,
    FAILED,
    ICP_ONLY,
    INFORMATION,
    MODE,
    MODEL_INVERSE,
    ORIGINAL_CODE,
    PAPER_METRES,
    PREVIOUS_INVERSE,
    RGBD_ONLY,
    STATUS,
    TOO_FEW,
    blocks_total,
)
from kintinuous_fast.odometry.solve import SOLVED
from kintinuous_fast.odometry.solve.ops import SCRATCH_MATRICES
from kintinuous_fast.odometry.solve.ops import build_ops as build_solve_ops
from kintinuous_fast.odometry.sums import NV, SLOT_B, SLOT_COST, SLOT_COUNT
from kintinuous_fast.odometry.sums.cuda import DEVICE
from kintinuous_fast.targets.cuda import kernel
from kintinuous_ref.odometry.combined import MIN_ICP_SCALE

# The block: two warps (one per estimator) per range of partials. Four ranges keep each
# thread's chain of loads a quarter as long as one warp's over a frame's 1024 blocks.
WARPS_PER_RANGE = 2
SOLVE_THREADS = 256
RANGES = SOLVE_THREADS // (32 * WARPS_PER_RANGE)
# The shared 6x6 systems: ICP's, RGB-D's and the joint one, and their right-hand sides (with
# the increment xi); the new pose.
ICP_SYSTEM, RGBD_SYSTEM, JOINT_SYSTEM, INCREMENT = range(4)


@cuda.jit(device=True)
def _barrier():
    cuda.syncthreads()


_ops = build_solve_ops(DEVICE, _barrier)
# Module-level names: numba resolves the device functions as globals of the kernels below.
_scaled_solution = _ops.scaled_solution
_discounted_joint = _ops.discounted_joint
_increment = _ops.increment


@cuda.jit(device=True)
def _add_partials(t, icp_partials, rgbd_partials, ranges, sums):
    """sums[0] = ICP's block partials added, sums[1] = RGB-D's: warp pair r adds range r of the
    blocks (ICP's warp first), one slot per thread, then the ranges are added in order."""
    warp, slot = t // 32, t % 32
    estimator, part = warp % 2, warp // 2
    if slot < NV:
        partials = icp_partials if estimator == 0 else rgbd_partials
        blocks = partials.shape[0]
        start, stop = part * blocks // RANGES, (part + 1) * blocks // RANGES
        ranges[estimator, part, slot] = blocks_total(partials, slot, start, stop)
    cuda.syncthreads()
    for e in range(t, 2 * NV, SOLVE_THREADS):
        estimator, slot = e // NV, e % NV
        total = ranges[estimator, 0, slot]
        for part in range(1, RANGES):
            total += ranges[estimator, part, slot]
        sums[estimator, slot] = total
    cuda.syncthreads()


@cuda.jit(device=True)
def _upper_slot(i, j):
    """The slot of A[i, j] in the summed vector: the upper triangle row by row (sums.unpack)."""
    row, column = min(i, j), max(i, j)
    return row * 6 - row * (row - 1) // 2 + column - row


@cuda.jit(device=True)
def _unpack(t, sums, systems, vectors):
    """ICP's and RGB-D's A and b from the summed vectors (sums.unpack), an element a thread."""
    for e in range(t, 36, SOLVE_THREADS):
        i, j = e // 6, e % 6
        for estimator in range(2):
            systems[estimator, i, j] = sums[estimator, _upper_slot(i, j)]
            if j == 0:
                vectors[estimator, i] = sums[estimator, SLOT_B + i]
    cuda.syncthreads()


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
    DISCOUNTED also shrinks ICP's weak directions (ops.discounted_joint)."""
    if weighting == PAPER_METRES:
        return 1.0, 1.0, rgbd_weight
    if weighting == ORIGINAL_CODE:
        return icp_code_scale * icp_code_scale, icp_code_scale, 1.0
    icp_weight = 1.0 / _scale_of(sums, 0, MIN_ICP_SCALE) ** 2
    if weighting == INFORMATION:
        return icp_weight, icp_weight, rgbd_weight / _scale_of(sums, 1, 1e-6) ** 2
    return icp_weight, icp_weight, rgbd_weight


@cuda.jit(device=True)
def _system(t, sums, mode, settings, pose, basis, systems, vectors, scratch):
    """The step's normal equations into systems[JOINT_SYSTEM], vectors[JOINT_SYSTEM] and their
    row count: ICP's, RGB-D's or the joint system of the two (combined.joint_system with
    settings' weighting; the discount's eigenproblem starts from `basis` and leaves its
    eigenvectors there). Every thread calls it and gets the same count."""
    _unpack(t, sums, systems, vectors)
    a, b = systems[JOINT_SYSTEM], vectors[JOINT_SYSTEM]
    icp_a, icp_b = systems[ICP_SYSTEM], vectors[ICP_SYSTEM]
    rgbd_a, rgbd_b = systems[RGBD_SYSTEM], vectors[RGBD_SYSTEM]
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
                pose[0, 3], pose[1, 3], pose[2, 3], threshold, basis, a, b, scratch, t,
                SOLVE_THREADS,
            )  # fmt: skip
            return sums[0, SLOT_COUNT] + sums[1, SLOT_COUNT]
    for e in range(t, 36, SOLVE_THREADS):
        i, j = e // 6, e % 6
        a[i, j] = icp_a[i, j] * scale_a + rgbd_a[i, j] * rgbd_scale
        if j == 0:
            b[i] = icp_b[i] * scale_b + rgbd_b[i] * rgbd_scale
    cuda.syncthreads()
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
def solve_kernel(icp_partials, rgbd_partials, tally, state, poses, basis, settings, level):
    """One Gauss-Newton step (solve.refine's loop body) on a block of SOLVE_THREADS: the
    partial sums added, the system formed and solved, the increment applied; the gate closed on
    failure or convergence. `settings` = (min_count, converged, weighting, rgbd_weight, original
    code's ICP scale, degeneracy threshold). `basis` (6, 6): the eigenvectors of the last
    step's discount (the identity at a frame's start), where this step's eigenproblem starts:
    consecutive steps' information matrices are close, so it takes fewer Jacobi sweeps."""
    t = cuda.threadIdx.x
    ranges = cuda.shared.array((2, RANGES, NV), float64)
    sums = cuda.shared.array((2, NV), float64)
    systems = cuda.shared.array((3, 6, 6), float64)
    vectors = cuda.shared.array((4, 6), float64)
    scratch = cuda.shared.array((SCRATCH_MATRICES, 6, 6), float64)
    updated = cuda.shared.array((4, 4), float64)
    # Every thread reads the gate before the first barrier; thread 0 writes it after the last.
    if state[FAILED] != 0.0 or state[DONE_LEVEL] == level:
        return
    _add_partials(t, icp_partials, rgbd_partials, ranges, sums)
    min_count, converged = settings[0], settings[1]
    mode = int(state[MODE])
    count = _system(t, sums, mode, settings, poses[0], basis, systems, vectors, scratch)
    if t == 0:
        tally[0] = 0.0  # the next step's Algorithm 2 lists from zero
        tally[1] = 0.0
    if count < min_count:
        if t == 0:
            _fail(state, TOO_FEW, level, 0.0, count)
        return
    xi = vectors[INCREMENT]
    status, condition = _scaled_solution(
        systems[JOINT_SYSTEM], vectors[JOINT_SYSTEM], xi, scratch, t, SOLVE_THREADS
    )
    if t != 0:
        return
    if status != SOLVED:
        _fail(state, status, level, condition, count)
        return
    _increment(xi, poses[0], updated, scratch)
    _update_poses(poses, updated)
    norm = math.sqrt(xi[0] ** 2 + xi[1] ** 2 + xi[2] ** 2 + xi[3] ** 2 + xi[4] ** 2 + xi[5] ** 2)
    if norm < converged:
        state[DONE_LEVEL] = level


__all__ = ["SOLVE_THREADS", "solve_kernel"]
