# ruff: noqa: ANN001, ANN201  (numba kernels: argument types come from the call)
"""One dense estimate on the device: kintinuous_ref.odometry.estimate_dense's steps (the
stale-stream test, coarse-to-fine Gauss-Newton, the inlier count at the finest level) as a
fixed sequence of CUDA kernels, each leaving its result where the next one reads it. The host
launches the sequence and waits once, for a record of 32 numbers: the pose, how the frame
ended and the counts the inlier check needs. The reference's loop (solve.refine) downloads
each iteration's system, solves it on the host and uploads the next pose: two waits and a
dozen launches' worth of Python per iteration, which on a GPU cost more than the kernels.

The sequence of a frame, the bracketed kernels only for a method with that estimator:

    begin, repeats, mode                        the state zeroed; which streams are fresh
    per level with steps, coarsest first:
        [interest, interest data]               Algorithm 1 into the level's fixed lists
        per step: [icp], [correspond, rows], solve
    at the finest level: [icp], [correspond], finish

`solve` runs in one block (frame_solve.py): it adds the blocks' partial sums in float64, forms
the joint system (kintinuous_ref.odometry.combined.joint_system, every weighting), solves it as
solve.solve does, applies the increment (eq. 4) and writes the new pose with the relative poses
ICP and RGB-D read. Where the reference leaves a level early (a step below
tracking.converged_step) or fails (no solution), the solve kernel closes the gate
(sums.cuda.gated) and the level's or the frame's remaining kernels return at once: the launches
stay the same for every frame, so the sequence is captured once and replayed.

The sequence is a function of its plan (FrameOnDevice.plan: the method, the iteration counts,
the settings and each level's kernel arguments, each once) and the workspace, so it is a signed
segment (targets.cuda_graphs.signed): once its graph exists, a frame with the same plan replays
it without the Python that launches and keys its hundred-odd kernels.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from numba import cuda

from kintinuous_fast.odometry.combined import CombinedProblem
from kintinuous_fast.odometry.frame_kernels import (  # the state's slots and the kernels
    CONDITION,
    DEPTH_DIFFERS,
    DEPTH_SEEN,
    FAIL_COUNT,
    FAIL_LEVEL,
    FAILED,
    ICP_ONLY,
    ICP_PAIRS,
    ICP_VALID,
    INTENSITY_DIFFERS,
    JOINT,
    METHOD_MODES,
    MODE,
    MODEL_INVERSE,
    PAPER_METRES,
    POSE,
    POSES_ICP,
    POSES_RGBD,
    PREVIOUS_INVERSE,
    RGBD_ONLY,
    RGBD_PAIRS,
    RGBD_POINTS,
    STALE,
    STATE_SIZE,
    STATUS,
    WEIGHTING_CODES,
    begin_kernel,
    finish_kernel,
    mode_kernel,
    repeats_kernel,
)
from kintinuous_fast.odometry.frame_solve import SOLVE_THREADS, solve_kernel
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
from kintinuous_fast.odometry.solve import failure_reason
from kintinuous_fast.odometry.sums import NV
from kintinuous_fast.odometry.sums.cuda import (
    ANY_LEVEL,
    BLOCK,
    reduction_blocks,
    stage,
)
from kintinuous_fast.targets import pinhole, to_host
from kintinuous_fast.targets.cuda import BLOCK_2D, copy_up, grid_1d, grid_2d
from kintinuous_fast.targets.cuda_graphs import signed

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
    and reused by every frame (the host then allocates nothing per frame). `token` tells
    workspaces apart in a signature: a number no other workspace of the process has."""

    made = 0

    def __init__(self, shapes: tuple[tuple[int, int], ...], uses_icp: bool, uses_rgbd: bool):
        Workspace.made += 1
        self.token = Workspace.made
        self.state = cuda.to_device(np.zeros(STATE_SIZE))
        self.poses = cuda.to_device(np.zeros((7, 4, 4)))
        self.icp_poses, self.rgbd_poses = self.poses[POSES_ICP], self.poses[POSES_RGBD]
        self.flags = cuda.to_device(np.zeros(3, dtype=np.int32))
        self.counts = cuda.to_device(np.zeros(len(shapes), dtype=np.int32))
        self.tally = cuda.to_device(np.zeros(2))
        self.basis = cuda.to_device(np.eye(6))  # the solve kernel's warm start
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


def _initial_poses(
    previous_pose: np.ndarray, icp: IcpProblem | None, start_pose: np.ndarray | None = None
) -> np.ndarray:
    """The poses array at the start of a frame: the estimate = `start_pose` (None: the previous
    pose), the relative poses as the host-driven kernels compute them, the inverses the solve
    kernel uses."""
    poses = np.zeros((7, 4, 4))
    model_inverse = icp.model_inverse if icp is not None else np.eye(4)
    start = previous_pose if start_pose is None else start_pose
    poses[0] = poses[3] = start
    poses[4] = previous_pose
    poses[1] = model_inverse @ start
    poses[2] = relative_pose(start, previous_pose)
    poses[PREVIOUS_INVERSE] = np.linalg.inv(previous_pose)
    poses[MODEL_INVERSE] = model_inverse
    return poses


class FrameOnDevice:
    """estimate_dense's launches for one frame (the module docstring's sequence): `upload` the
    previous pose, `launch` the kernels, download the `record`. `launch` copies nothing and
    waits for nothing, and its buffers are the workspace's and the frames' own, so from one frame
    to the next (the frames' buffers pooled) its launches repeat and, with graphs on, replay as
    one CUDA graph (targets.cuda_graphs)."""

    def __init__(self, tracker: Any, problem: Any, previous: Any, current: Any) -> None:
        self.tracker, self.problem = tracker, problem
        self.icp, self.rgbd = _parts(problem)
        self.levels = current.levels[: len(tracker.iterations)]
        shapes = tuple(tuple(level.depth.shape) for level in self.levels)
        self.space = workspace(shapes, self.icp is not None, self.rgbd is not None)
        self.previous, self.current = previous, current
        self.settings = _settings(tracker, problem)
        self._arguments: dict[int, tuple] = {}  # per level: (ICP's, RGB-D's) kernel arguments

    def run(self, previous_pose: np.ndarray, start_pose: np.ndarray | None = None) -> np.ndarray:
        """The frame's record (32 numbers, the module's slots) for an estimate started at
        `start_pose` (None: `previous_pose`): its one upload, its launches and its one wait."""
        self.upload(previous_pose, start_pose)
        self.launch()
        return self.record()

    def upload(self, previous_pose: np.ndarray, start_pose: np.ndarray | None = None) -> None:
        """The frame's poses (_initial_poses) into the workspace."""
        copy_up(self.space.poses, _initial_poses(previous_pose, self.icp, start_pose))

    def record(self) -> np.ndarray:
        """The state vector on the host: the one wait for the device."""
        return to_host(self.space.state)

    def launch(self) -> None:
        """Every kernel of the frame, in order: a signed segment (targets.cuda_graphs.signed)
        whose signature is the workspace and the plan, so that with graphs on a frame whose
        plan repeats an earlier one's replays without running the Python that launches."""
        plan = self.plan()
        signed("dense estimate", (self.space.token, plan), lambda: self._launch(plan))

    def plan(self) -> tuple:
        """Everything the frame's launches take beyond the workspace, each once: (method,
        iterations, finest level, solve settings, the stale-stream test's images, per level
        None or (pixels, Algorithm 1's arguments or None, ICP's and RGB-D's kernel arguments))."""
        iterations, finest = tuple(self.tracker.iterations), self.tracker.finest_level
        before, now = self.previous.levels[0], self.current.levels[0]
        repeats = (stage(before.depth), now.depth, stage(before.intensity), now.intensity)
        levels = tuple(
            (self._pixels(level), self._interest_arguments(level), *self.arguments(level))
            if iterations[level] or level == finest
            else None
            for level in range(len(iterations))
        )
        method = METHOD_MODES[self.tracker.method]
        return (method, iterations, finest, self.settings, repeats, levels)

    def _launch(self, plan: tuple) -> None:
        """The launches of `plan` (and the workspace): nothing else may vary them."""
        method, iterations, finest, settings, repeats, levels = plan
        space = self.space
        begin_kernel[1, 1](space.state, space.flags, space.counts, space.tally, space.basis)
        repeats_kernel[grid_2d(*repeats[1].shape), BLOCK_2D](*repeats, space.flags)
        mode_kernel[1, 1](space.flags, space.state, method)
        for level in reversed(range(len(iterations))):
            if levels[level] is None:
                continue
            pixels, interest, icp_arguments, rgbd_arguments = levels[level]
            if interest is not None:
                interest_kernel[grid_1d(pixels, BLOCK), BLOCK](*interest[0])
                interest_data_kernel[grid_1d(pixels, BLOCK), BLOCK](*interest[1])
            partials = space.levels[level]
            for _ in range(iterations[level]):
                self._systems(levels[level], level, level)
                solve_kernel[1, SOLVE_THREADS](
                    partials.icp_partials,
                    partials.rgbd_partials,
                    space.tally,
                    space.state,
                    space.poses,
                    space.basis,
                    settings,
                    level,
                )
        self._systems(levels[finest], finest, ANY_LEVEL, rows=False)
        finish_kernel[1, 1](
            space.levels[finest].icp_partials,
            space.tally,
            space.counts,
            space.state,
            space.poses,
            finest,
        )

    def _pixels(self, level: int) -> int:
        return self.levels[level].camera.height * self.levels[level].camera.width

    def _interest_arguments(self, level: int) -> tuple | None:
        """Algorithm 1's two kernels' arguments at `level` (rgbd/cuda.py's kernels: into the
        level's fixed lists), None without RGB-D."""
        if self.rgbd is None:
            return None
        rgbd, image = self.rgbd, self.levels[level]
        buffers = self.space.levels[level]
        threshold = rgbd.min_gradient[min(level, len(rgbd.min_gradient) - 1)]
        depth, dx, dy = stage(image.depth), stage(image.intensity_dx), stage(image.intensity_dy)
        select = (
            dx, dy, depth, float(threshold) ** 2, True, float(rgbd.max_depth), buffers.count,
            buffers.indices,
        )  # fmt: skip
        gather = (
            buffers.indices, buffers.count, depth, stage(image.intensity), dx, dy,
            pinhole(image.camera), buffers.points, buffers.values, buffers.gradient,
        )  # fmt: skip
        return select, gather

    def _systems(self, planned: tuple, level: int, gate_level: int, rows: bool = True) -> None:
        """ICP's block partials and RGB-D's pair list (and, with `rows`, its block partials)
        at `level` (`planned`: its entry of the plan) for the estimate on the device;
        `gate_level` = the level whose convergence skips them, ANY_LEVEL for the inlier check."""
        space, buffers = self.space, self.space.levels[level]
        pixels, _, icp_arguments, rgbd_arguments = planned
        if icp_arguments is not None:
            icp_kernel[reduction_blocks(pixels), BLOCK](*icp_arguments, space.state, gate_level)
        if rgbd_arguments is None:
            return
        correspond_kernel[grid_1d(pixels, BLOCK), BLOCK](
            *rgbd_arguments, space.tally, buffers.pairs, space.state, gate_level
        )
        if rows:
            rows_kernel[reduction_blocks(pixels), BLOCK](
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
    least = tracker.config.tracking.min_correspondences
    return failure_reason(status, float(record[CONDITION]), count, least)


def estimate_on_device(
    tracker: Any,
    previous: Any,
    current: Any,
    model: Any,
    previous_pose: np.ndarray,
    start_pose: np.ndarray | None = None,
) -> tuple[np.ndarray, str]:
    """kintinuous_ref.odometry.estimate_dense with every step on the device and one wait."""
    problem = tracker.problem(previous, current, model, previous_pose)
    frame = FrameOnDevice(tracker, problem, previous, current)
    start = None if start_pose is None else np.ascontiguousarray(start_pose, dtype=np.float64)
    record = frame.run(np.ascontiguousarray(previous_pose, dtype=np.float64), start)
    return read_record(tracker, record, previous_pose)


__all__ = ["FrameOnDevice", "Workspace", "estimate_on_device", "read_record", "workspace"]
