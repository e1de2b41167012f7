# ruff: noqa: ANN001, ANN201  (numba kernels: argument types come from the call)
"""One dense estimate on the device: kintinuous_ref.odometry.estimate_dense's steps (the
stale-stream test, coarse-to-fine Gauss-Newton, the inlier count at the finest level) as a
fixed sequence of CUDA kernels, each leaving its result where the next one reads it. The host
launches the sequence and waits once, for a record of 80 numbers: the pose, how the frame
ended and the counts the inlier check needs. The reference's loop (solve.refine) downloads
each iteration's system, solves it on the host and uploads the next pose: two waits and a
dozen launches' worth of Python per iteration, which on a GPU cost more than the kernels.

The sequence of a frame, the bracketed kernels only for a method with that estimator:

    begin, repeats, mode                        the state zeroed; which streams are fresh
    per level with steps, coarsest first:
        [interest, interest data]               Algorithm 1 into the level's fixed lists
        per step: [icp], [correspond, rows], solve
    at the finest level: [icp], [correspond], finish

`solve` runs in one block: it adds the blocks' partial sums in float64, forms the joint system
(kintinuous_ref.odometry.combined.joint_system, every weighting), solves it as solve.solve
does, applies the increment (eq. 4) and writes the new pose with the relative poses ICP and
RGB-D read. Where the reference leaves a level early (a step below tracking.converged_step) or
fails (no solution), the solve kernel closes the gate (sums.cuda.gated) and the level's or the
frame's remaining kernels return at once: the launches stay the same for every frame, so the
sequence could be captured once and replayed.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from numba import cuda, float64

from kintinuous_fast.odometry.combined import CombinedProblem
from kintinuous_fast.odometry.icp.cuda import IcpProblem, icp_kernel
from kintinuous_fast.odometry.rgbd import relative_pose
from kintinuous_fast.odometry.rgbd.cuda import (
    RgbdProblem,
    correspond_kernel,
    interest_data_kernel,
    interest_kernel,
    pair_arguments,
    rows_kernel,
)
from kintinuous_fast.odometry.solve import SOLVED, solve_reasons
from kintinuous_fast.odometry.solve.ops import SCRATCH_MATRICES
from kintinuous_fast.odometry.solve.ops import build_ops as build_solve_ops
from kintinuous_fast.odometry.sums import NV, SLOT_B, SLOT_COST, SLOT_COUNT, SLOT_EXTRA
from kintinuous_fast.odometry.sums.cuda import (
    ANY_LEVEL,
    BLOCK,
    DEVICE,
    GATE_DONE_LEVEL,
    GATE_FAILED,
    reduction_blocks,
    stage,
)
from kintinuous_fast.targets import pinhole, to_host
from kintinuous_fast.targets.cuda import BLOCK_2D, grid_1d, grid_2d, kernel
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
SOLVE_THREADS = 32  # the solve and finish kernels' block: one thread per slot of the sums

_ops = build_solve_ops(DEVICE)
# Module-level names: numba resolves the device functions as globals of the kernels below.
_scaled_solution = _ops.scaled_solution
_discounted_joint = _ops.discounted_joint
_increment = _ops.increment


# ----------------------------------------------------------------------------------------------
# Kernels


@kernel
def _begin_kernel(state, flags, counts, tally):
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
def _mode_kernel(flags, state, method):
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
def _add_partials(partials, sums, row):
    """sums[row, s] = the blocks' partials of slot s added in block order, one slot per
    thread of the block."""
    for s in range(cuda.threadIdx.x, NV, cuda.blockDim.x):
        total = 0.0
        for k in range(partials.shape[0]):
            total += partials[k, s]
        sums[row, s] = total


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
def _solve_kernel(icp_partials, rgbd_partials, tally, state, poses, settings, level):
    """One Gauss-Newton step (solve.refine's loop body) in one block: the partial sums added,
    the system formed and solved, the increment applied; the gate closed on failure or
    convergence. `settings` = (min_count, converged, weighting, rgbd_weight, original code's
    ICP scale, degeneracy threshold)."""
    sums = cuda.shared.array((2, NV), float64)
    if state[FAILED] != 0.0 or state[DONE_LEVEL] == level:
        return
    _add_partials(icp_partials, sums, 0)
    _add_partials(rgbd_partials, sums, 1)
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
def _finish_kernel(icp_partials, tally, counts, state, poses, finest):
    """The record: the inlier check's counts at the finest level and the estimate; one thread."""
    pairs = 0.0
    valid = 0.0
    for k in range(icp_partials.shape[0]):
        pairs += icp_partials[k, SLOT_COUNT]
        valid += icp_partials[k, SLOT_EXTRA]
    state[ICP_PAIRS] = pairs
    state[ICP_VALID] = valid
    state[RGBD_PAIRS] = tally[0]
    state[RGBD_POINTS] = counts[finest]
    for i in range(4):
        for j in range(4):
            state[POSE + 4 * i + j] = poses[0, i, j]


# ----------------------------------------------------------------------------------------------
# Host side


@dataclass
class _Level:
    """One pyramid level's fixed device buffers: ICP's block partials and, for RGB-D, the
    interest lists (room for every pixel), the pair list and its block partials."""

    icp_partials: Any
    indices: Any = None
    points: Any = None
    values: Any = None
    gradient: Any = None
    pairs: Any = None
    rgbd_partials: Any = None
    count: Any = None  # the level's slot of Workspace.counts (its interest points)


class Workspace:
    """Every device buffer one frame's estimate uses, made once per camera pyramid and method
    and reused by every frame (the host then allocates nothing per frame)."""

    def __init__(self, shapes: tuple[tuple[int, int], ...], uses_icp: bool, uses_rgbd: bool):
        self.state = cuda.to_device(np.zeros(STATE_SIZE))
        self.poses = cuda.to_device(np.zeros((7, 4, 4)))
        self.icp_poses, self.rgbd_poses = self.poses[POSES_ICP], self.poses[POSES_RGBD]
        self.flags = cuda.to_device(np.zeros(3, dtype=np.int32))
        self.counts = cuda.to_device(np.zeros(len(shapes), dtype=np.int32))
        self.tally = cuda.to_device(np.zeros(2))
        self.no_partials = cuda.to_device(np.zeros((1, NV)))
        self.levels = [self._level(h * w, uses_icp, uses_rgbd) for h, w in shapes]
        for index, level in enumerate(self.levels):  # a view made once: numba's cost per view
            level.count = self.counts[index : index + 1]

    def _level(self, pixels: int, uses_icp: bool, uses_rgbd: bool) -> _Level:
        blocks = reduction_blocks(pixels)
        level = _Level(cuda.device_array((blocks, NV)) if uses_icp else self.no_partials)
        if uses_rgbd:
            level.indices = cuda.device_array(pixels, dtype=np.int64)
            level.points = cuda.device_array((3, pixels))
            level.values = cuda.device_array(pixels)
            level.gradient = cuda.device_array((2, pixels))
            level.pairs = cuda.device_array(pixels, dtype=np.int64)
            level.rgbd_partials = cuda.device_array((blocks, NV))
        else:
            level.rgbd_partials = self.no_partials
        return level


_WORKSPACES: dict[tuple, Workspace] = {}


def workspace(shapes: tuple[tuple[int, int], ...], uses_icp: bool, uses_rgbd: bool) -> Workspace:
    """The workspace of this pyramid and method, made on first use."""
    key = (shapes, uses_icp, uses_rgbd)
    if key not in _WORKSPACES:
        _WORKSPACES[key] = Workspace(shapes, uses_icp, uses_rgbd)
    return _WORKSPACES[key]


def _parts(problem: Any) -> tuple[IcpProblem | None, RgbdProblem | None]:
    """The problem's ICP and RGB-D halves (None where the method has none)."""
    if isinstance(problem, CombinedProblem):
        return problem.icp, problem.rgbd
    if isinstance(problem, IcpProblem):
        return problem, None
    return None, problem


def _settings(tracker: Any, problem: Any) -> tuple:
    """The solve kernel's settings tuple (its docstring): the tracking limits and, for a joint
    problem, its weighting (a single estimator's system is solved as it is)."""
    limits = (
        float(tracker.config.tracking.min_correspondences),
        float(tracker.config.tracking.converged_step),
    )
    if not isinstance(problem, CombinedProblem):
        return (*limits, PAPER_METRES, 1.0, 1.0, 0.0)
    return (
        *limits,
        WEIGHTING_CODES[problem.weighting],
        float(problem.rgbd_weight),
        float(problem.original_code_icp_scale),
        float(problem.degeneracy_threshold),
    )


def _initial_poses(previous_pose: np.ndarray, icp: IcpProblem | None) -> np.ndarray:
    """The poses array at the start of a frame: the estimate = the previous pose, the relative
    poses as the host-driven kernels compute them, the inverses the solve kernel uses."""
    poses = np.zeros((7, 4, 4))
    model_inverse = icp.model_inverse if icp is not None else np.eye(4)
    poses[0] = poses[3] = poses[4] = previous_pose
    poses[1] = model_inverse @ previous_pose
    poses[2] = relative_pose(previous_pose, previous_pose)
    poses[PREVIOUS_INVERSE] = np.linalg.inv(previous_pose)
    poses[MODEL_INVERSE] = model_inverse
    return poses


class FrameOnDevice:
    """estimate_dense's launches for one frame (the module docstring's sequence): `upload` the
    previous pose, `launch` the kernels, download the `record`. `launch` copies nothing and
    waits for nothing, and its buffers are the workspace's and the frames' own, so its kernels
    can be captured on a stream as a CUDA graph and replayed (benchmarks/cuda_graph_frame.py).
    `stream`: numba's stream for every launch (0: the default stream)."""

    def __init__(
        self, tracker: Any, problem: Any, previous: Any, current: Any, stream: Any = 0
    ) -> None:
        self.tracker, self.problem, self.stream = tracker, problem, stream
        self.icp, self.rgbd = _parts(problem)
        self.levels = current.levels[: len(tracker.iterations)]
        shapes = tuple(tuple(level.depth.shape) for level in self.levels)
        self.space = workspace(shapes, self.icp is not None, self.rgbd is not None)
        self.previous, self.current = previous, current
        self.settings = _settings(tracker, problem)
        self._arguments: dict[int, tuple] = {}  # per level: (ICP's, RGB-D's) kernel arguments

    def run(self, previous_pose: np.ndarray) -> np.ndarray:
        """The frame's record (32 numbers, the module's slots) for an estimate started at
        `previous_pose`: its one upload, its launches and its one wait."""
        self.upload(previous_pose)
        self.launch()
        return self.record()

    def upload(self, previous_pose: np.ndarray) -> None:
        """The frame's poses (_initial_poses) into the workspace."""
        poses = _initial_poses(previous_pose, self.icp)
        self.space.poses.copy_to_device(poses, stream=self.stream)

    def record(self) -> np.ndarray:
        """The state vector on the host: the one wait for the device."""
        return to_host(self.space.state)

    def launch(self) -> None:
        """Every kernel of the frame, in order, on the stream."""
        space, stream = self.space, self.stream
        _begin_kernel[1, 1, stream](space.state, space.flags, space.counts, space.tally)
        before, now = self.previous.levels[0], self.current.levels[0]
        repeats_kernel[grid_2d(*now.depth.shape), BLOCK_2D, stream](
            stage(before.depth), now.depth, stage(before.intensity), now.intensity, space.flags
        )
        method = METHOD_MODES[self.tracker.method]
        _mode_kernel[1, 1, stream](space.flags, space.state, method)
        iterations = self.tracker.iterations
        finest = self.tracker.finest_level
        for level in reversed(range(len(iterations))):
            if iterations[level] or level == finest:
                self._interest_points(level)
            for _ in range(iterations[level]):
                self._systems(level, level)
                partials = space.levels[level]
                _solve_kernel[1, SOLVE_THREADS, stream](
                    partials.icp_partials,
                    partials.rgbd_partials,
                    space.tally,
                    space.state,
                    space.poses,
                    self.settings,
                    level,
                )
        self._systems(finest, ANY_LEVEL, rows=False)
        _finish_kernel[1, 1, stream](
            space.levels[finest].icp_partials,
            space.tally,
            space.counts,
            space.state,
            space.poses,
            finest,
        )

    def _interest_points(self, level: int) -> None:
        """Algorithm 1 at `level` into the level's fixed lists (rgbd/cuda.py's kernels)."""
        if self.rgbd is None:
            return
        rgbd, image = self.rgbd, self.levels[level]
        buffers = self.space.levels[level]
        count = buffers.count
        threshold = rgbd.min_gradient[min(level, len(rgbd.min_gradient) - 1)]
        depth, dx, dy = stage(image.depth), stage(image.intensity_dx), stage(image.intensity_dy)
        pixels = image.depth.shape[0] * image.depth.shape[1]
        interest_kernel[grid_1d(pixels, BLOCK), BLOCK, self.stream](
            dx, dy, depth, float(threshold) ** 2, True, float(rgbd.max_depth), count,
            buffers.indices,
        )  # fmt: skip
        interest_data_kernel[grid_1d(pixels, BLOCK), BLOCK, self.stream](
            buffers.indices, count, depth, stage(image.intensity), dx, dy,
            pinhole(image.camera), buffers.points, buffers.values, buffers.gradient,
        )  # fmt: skip

    def _systems(self, level: int, gate_level: int, rows: bool = True) -> None:
        """ICP's block partials and RGB-D's pair list (and, with `rows`, its block partials)
        at `level` for the estimate on the device; `gate_level` = the level whose convergence
        skips them, ANY_LEVEL for the inlier check."""
        space, buffers = self.space, self.space.levels[level]
        pixels = self.levels[level].camera.height * self.levels[level].camera.width
        icp_arguments, rgbd_arguments = self.arguments(level)
        if icp_arguments is not None:
            icp_kernel[reduction_blocks(pixels), BLOCK, self.stream](
                *icp_arguments, space.state, gate_level
            )
        if rgbd_arguments is None:
            return
        correspond_kernel[grid_1d(pixels, BLOCK), BLOCK, self.stream](
            *rgbd_arguments, space.tally, buffers.pairs, space.state, gate_level
        )
        if rows:
            rows_kernel[reduction_blocks(pixels), BLOCK, self.stream](
                buffers.pairs, space.tally, *rgbd_arguments, buffers.rgbd_partials, space.state,
                gate_level,
            )  # fmt: skip

    def arguments(self, level: int) -> tuple:
        """(ICP kernel's arguments but the gate, RGB-D's pair arguments) at `level`, None for
        an estimator the method lacks: staged and assembled once per frame, not per step."""
        if level not in self._arguments:
            space, buffers = self.space, self.space.levels[level]
            icp_arguments = rgbd_arguments = None
            if self.icp is not None:
                icp, camera = self.icp, self.levels[level].camera
                limits = icp.constants(np.eye(4))[2:]  # (squared distance, cos angle)
                icp_arguments = (
                    *icp.points(level), space.icp_poses, *icp.model(level), pinhole(camera),
                    limits, icp.robust, buffers.icp_partials,
                )  # fmt: skip
            if self.rgbd is not None:
                interest = (buffers.points, buffers.count, buffers.values, buffers.gradient)
                rgbd_arguments = pair_arguments(
                    interest,
                    space.rgbd_poses,
                    self.rgbd.previous(level),
                    self.rgbd.previous_levels[level].camera,
                    self.rgbd.max_depth_change,
                )
            self._arguments[level] = (icp_arguments, rgbd_arguments)
        return self._arguments[level]


def read_record(tracker: Any, record: np.ndarray, previous_pose: np.ndarray) -> tuple:
    """(pose, reason) of a frame's record, as estimate_dense words them."""
    from kintinuous_ref.odometry import stale_input

    mode = int(record[MODE])
    if mode == STALE:
        seen = record[DEPTH_SEEN] != 0
        depth_repeated = bool(seen and record[DEPTH_DIFFERS] == 0)
        colour_repeated = bool(seen and record[INTENSITY_DIFFERS] == 0)
        return previous_pose.copy(), stale_input(tracker.method, depth_repeated, colour_repeated)
    pose = record[POSE : POSE + 16].reshape(4, 4).copy()
    if record[FAILED]:
        return pose, f"level {int(record[FAIL_LEVEL])}: {_failure(tracker, record)}"
    icp = record[ICP_PAIRS] / record[ICP_VALID] if record[ICP_VALID] else 0.0
    rgbd = record[RGBD_PAIRS] / record[RGBD_POINTS] if record[RGBD_POINTS] else 0.0
    fraction = {JOINT: max(icp, rgbd), ICP_ONLY: icp, RGBD_ONLY: rgbd}[mode]
    return pose, tracker.check_estimate(pose, previous_pose, fraction)


def _failure(tracker: Any, record: np.ndarray) -> str:
    """The reason of a failed step (solve.solve's wording)."""
    status, count = int(record[STATUS]), int(round(record[FAIL_COUNT]))
    if status == TOO_FEW:
        return f"too few correspondences ({count} < {tracker.config.tracking.min_correspondences})"
    return solve_reasons(float(record[CONDITION]))[status]


def estimate_on_device(
    tracker: Any, previous: Any, current: Any, model: Any, previous_pose: np.ndarray
) -> tuple[np.ndarray, str]:
    """kintinuous_ref.odometry.estimate_dense with every step on the device and one wait."""
    problem = tracker.problem(previous, current, model, previous_pose)
    frame = FrameOnDevice(tracker, problem, previous, current)
    record = frame.run(np.ascontiguousarray(previous_pose, dtype=np.float64))
    return read_record(tracker, record, previous_pose)


__all__ = ["FrameOnDevice", "Workspace", "estimate_on_device", "read_record", "workspace"]
