# ruff: noqa: ANN001, ANN201  (numba loops: argument types come from the call)
"""One iteration of the joint ICP + RGB-D estimate on the CPU (combined.CombinedProblem.system
over the CPU's problems): both systems in one parallel call, and their sums, the ICP scale and
the degeneracy-aware joint system (combined.joint_system's default weightings) in one compiled
function.

Called apart, the two problems cost two wake-ups of the other threads per iteration, and about
forty NumPy and Python calls between them (partials made and added up, LinearSystems unpacked,
scaled and summed) that each take microseconds for nanoseconds of arithmetic. Here one loop
runs the RGB-D correspondence chunks, then the ICP chunks, then the RGB-D rows chunks (rgbd/
cpu.py's second pass, which needs every correspondence chunk's sum: with the ICP chunks
between, its threads seldom wait), and a level's work arrays are made once for all of its
iterations. The chunks and the order of every sum are those of the separate calls, so the system is
the same, bit for bit, on any number of threads.

A whole level runs in one compiled call too (`_refine_level`, JointLevel.refine): each step's
poses, the joint loop on numba's threads, the sums and solve.refine's step, with no Python
between the steps. The ICP problem alone runs its levels the same way, through this loop with
its RGB-D part empty, and the RGB-D problem alone through its own two-pass loop. In the
pipeline the Python between two steps took 200-220 microseconds on the 2-core VM, at some 14
steps a frame; repeating one level in a loop, the compiled level was up to 360 microseconds a
step faster (docs/benchmarks.md).
"""

from __future__ import annotations

import math
import time
import weakref

import numba
import numpy as np

from kintinuous_fast.odometry.combined import _discounted_joint
from kintinuous_fast.odometry.rgbd.cpu import (
    WarpTerms,
    _correspond_chunk,
    _rgbd_system_loop,
    _robust_scale,
    _rows_chunk,
    _two_pass_parts,
    _work,
)
from kintinuous_fast.odometry.solve import SOLVED, failure_reason, gauss_newton_step
from kintinuous_fast.odometry.sums import NV, SLOT_B, SLOT_COST, SLOT_COUNT
from kintinuous_fast.odometry.sums.cpu import ALLOCATING_LOOP, partials
from kintinuous_fast.targets import pinhole
from kintinuous_fast.targets.cpu import (
    LOOP_COSTS,
    NEXT_PART,
    PARTS_DONE,
    SPINS,
    atomic_fetch_add,
    atomic_load,
    claim_slot,
    planned_team,
    run_on_threads,
    run_parallel,
    spin_below,
    start_numba_threads,
)
from kintinuous_ref.odometry.combined import MIN_ICP_SCALE
from kintinuous_ref.odometry.solve import LinearSystem
from kintinuous_ref.vocabulary import ROBUST_WEIGHTINGS

from . import NO_WEIGHTS
from .cpu_block import icp_chunk

__all__ = ["FUSED_WEIGHTINGS", "JointLevel", "joint_level", "joint_system"]

# The weightings whose joint system is computed here: the degeneracy-aware ones (the default
# among them); the others are a scaling and a sum, left to the reference's joint_system.
FUSED_WEIGHTINGS = ("degeneracy-aware", *ROBUST_WEIGHTINGS)


# ----------------------------------------------------------------------------------------------
# The loop


# Not cached, as targets.cpu.claimed_items (a generator).
@numba.njit
def _joint_items(claims, corresponded, parts, correspond, rows_from, spins):
    """The parts of one _joint_loop call this thread claims, one item each, in order: the
    RGB-D correspondence chunks (0..correspond-1, each counted in corresponded[0] when done),
    the ICP chunks, then from `rows_from` the RGB-D rows chunks, which read every
    correspondence chunk's sums: those are claimed once corresponded[0] reaches `correspond`,
    which the ICP chunks between leave time for. A thread that would wait for it longer than
    `spins` atomic loads (a thread holding a correspondence chunk descheduled) leaves the loop
    rather than spin on a core that thread needs; the thread that finishes the last
    correspondence chunk always goes on (as targets.cpu.claimed_items_in_passes)."""
    while True:
        if (
            atomic_load(claims, NEXT_PART) >= rows_from
            and spin_below(corresponded, 0, correspond, spins) < correspond
        ):
            return
        part = atomic_fetch_add(claims, NEXT_PART)
        if part >= parts:
            return
        if part >= rows_from:  # claimed between the look above and now: it must wait
            while spin_below(corresponded, 0, correspond, spins) < correspond:
                pass
        yield part
        if part < correspond:
            atomic_fetch_add(corresponded, 0)
        atomic_fetch_add(claims, PARTS_DONE)


@ALLOCATING_LOOP
def _joint_loop(
    claims, parts, corresponded, icp_terms, icp_out, rgbd_terms, pairs, sums, warps, rgbd_out
):
    """One item per part (_joint_items): the RGB-D correspondence chunks (_correspond_chunk),
    the ICP chunks (icp_chunk into icp_out), then the RGB-D rows chunks (_rows_chunk); a
    thread's first rows chunk takes sigma' from the correspondence chunks' sums.
    `corresponded`: the correspondence chunks done, zeroed before the call. `icp_terms` =
    (points, pose, current to model camera, model vertices, model normals, camera, limits,
    robust) as icp/cpu.py's loops take them, `rgbd_terms` = (the interest points' columns,
    warp terms, (previous pose, focal)) as rgbd/cpu.py's."""
    points, pose, to_model, mv, mn, camera, limits, robust = icp_terms
    columns, warp_terms, row_terms = rgbd_terms
    interest, intensity, gradient = columns
    previous_pose, focal = row_terms
    correspond = sums.shape[0]
    rows_from = correspond + icp_out.shape[0]
    warp = warps[claim_slot(claims)]
    sigma, has_pairs = -1.0, False
    for item in _joint_items(claims, corresponded, parts, correspond, rows_from, SPINS):
        if item < correspond:
            _correspond_chunk(item, interest, intensity, gradient, warp_terms, pairs, sums, warp)
        elif item < rows_from:
            c = item - correspond
            icp_chunk(c, points, pose, to_model, mv, mn, camera, limits, robust, icp_out)
        else:
            if sigma < 0.0:  # this thread's first rows chunk
                has_pairs, sigma = _robust_scale(sums)
            if has_pairs:
                _rows_chunk(item - rows_from, pairs, previous_pose, focal, sigma, rgbd_out)


# ----------------------------------------------------------------------------------------------
# The sums


@numba.njit(cache=True)
def _added_chunks(out):
    """The rows of `out` (chunks, NV) added in order, as NumPy adds them along axis 0
    (sums.sum_partials): each entry's sum runs over the chunks one after another."""
    total = np.zeros(out.shape[1])
    for c in range(out.shape[0]):
        for k in range(out.shape[1]):
            total[k] += out[c, k]
    return total


@numba.njit(cache=True)
def _unpacked(total):
    """(A, b, count, cost) of an NV vector, as sums.unpack."""
    a = np.empty((6, 6))
    slot = 0
    for i in range(6):
        for j in range(i, 6):
            a[i, j] = a[j, i] = total[slot]
            slot += 1
    return a, total[SLOT_B : SLOT_B + 6].copy(), int(np.rint(total[SLOT_COUNT])), total[SLOT_COST]


@numba.njit(cache=True)
def _icp_weight(count, cost):
    """1 / combined.icp_scale^2 of an ICP system, as the reference computes it (Python's
    max keeps its first argument unless the second is larger: a NaN scale stays NaN)."""
    if count == 0:
        return 1.0
    scale = math.sqrt(cost / count)
    scale = MIN_ICP_SCALE if MIN_ICP_SCALE > scale else scale
    return 1.0 / scale**2


@numba.njit(cache=True)
def _rgbd_total(sums, rgbd_out):
    """The RGB-D system's NV vector from rgbd_out, zeros where the first pass kept no pair
    (`sums`' counts), as rgbd/cpu.py's _system sums it."""
    pairs = 0.0
    for c in range(sums.shape[0]):
        pairs += sums[c, 1]
    return _added_chunks(rgbd_out) if pairs != 0.0 else np.zeros(NV)


@numba.njit(cache=True)
def _level_sums(kind, icp_out, sums, rgbd_out, weights, centre):
    """(A, b, count, cost) of the system a level of `kind` solves: the joint one (_joint_sums,
    `weights` = (rgbd_weight, degeneracy threshold)), or the ICP or the RGB-D system alone, as
    the problems' own `system` unpacks it."""
    if kind == ICP_ONLY:
        return _unpacked(_added_chunks(icp_out))
    if kind == RGBD_ONLY:
        return _unpacked(_rgbd_total(sums, rgbd_out))
    return _joint_sums(icp_out, sums, rgbd_out, weights[0], centre, weights[1])


@numba.njit(cache=True)
def _joint_sums(icp_out, sums, rgbd_out, rgbd_weight, centre, threshold):
    """(A, b, count, cost) of combined.joint_system's degeneracy-aware branch over the two
    loops' partial sums: the ICP system from icp_out, the RGB-D one from rgbd_out (empty where
    the first pass kept no pair: `sums`' counts), as the separate calls unpack them."""
    icp_a, icp_b, icp_count, icp_cost = _unpacked(_added_chunks(icp_out))
    rgbd_a, rgbd_b, rgbd_count, rgbd_cost = _unpacked(_rgbd_total(sums, rgbd_out))
    icp_weight = _icp_weight(icp_count, icp_cost)
    a, b = _discounted_joint(
        icp_a, icp_b, icp_count, icp_weight, rgbd_a, rgbd_b, rgbd_weight, centre, threshold
    )
    cost = icp_cost * icp_weight + rgbd_cost * rgbd_weight
    return a, b, icp_count + rgbd_count, cost


# ----------------------------------------------------------------------------------------------
# A level's iterations

# A status beside solve's (gauss_newton_step): a thread of the joint loop failed.
THREAD_FAILED = -1
# The system a level solves: both terms', or one's alone.
JOINT, ICP_ONLY, RGBD_ONLY = range(3)


@numba.njit(cache=True, nogil=True)
def _refine_level(kind, team, steps, min_count, converged, pose, fixed, work, weights):
    """solve.refine's loop over one level, every step in compiled code: the system of `kind` at
    the pose (_level_system), then gauss_newton_step, up to `steps` steps or until one is
    shorter than `converged`. Returns (pose, status, condition, count, the systems computed:
    the steps taken and a failed one)."""
    for step in range(steps):
        failed, a, b, count = _level_system(kind, team, pose, fixed, work, weights)
        if failed:
            return pose, THREAD_FAILED, 0.0, 0, step + 1
        status, condition, pose, length = gauss_newton_step(a, b, count, min_count, pose)
        if status != SOLVED:
            return pose, status, condition, count, step + 1
        if length < converged:
            return pose, SOLVED, 0.0, count, step + 1
    return pose, SOLVED, 0.0, 0, steps


@numba.njit(cache=True, nogil=True)
def _level_system(kind, team, pose, fixed, work, weights):
    """(whether a thread failed, A, b, count) of the system of `kind` at `pose`: the joint loop
    (the RGB-D problem alone: its own two-pass loop) on `team` threads (run_on_threads; the
    calling thread alone for 1), then _level_sums. The poses the loops read are those
    JointLevel.system passes, computed as NumPy does (np.dot is BLAS's product, as the @ of
    icp_constants and WarpTerms). `fixed` = (the ICP terms without pose and to_model, the model
    pose's inverse, the RGB-D columns, WarpTerms' fields, row terms), `work` = the level's work
    arrays and parts, `weights` = (rgbd_weight, degeneracy threshold)."""
    (points, mv, mn, camera, limits, robust), model_inverse, columns, warp, row_terms = fixed
    to_previous, images, warped, intrinsics, max_change = warp
    corresponded, icp_out, pairs, sums, warps, rgbd_out, parts = work
    warp_terms = (np.dot(to_previous, pose), pose, images, warped, intrinsics, max_change)
    claims = np.zeros(3, dtype=np.int64)
    failed = False
    if kind == RGBD_ONLY:
        interest, intensity, gradient = columns
        args = (interest, intensity, gradient, warp_terms, row_terms, pairs, sums, warps, rgbd_out)
        if team == 1:
            _rgbd_system_loop(claims, parts, *args)
        else:
            failed = run_on_threads(team, _rgbd_system_loop, claims, parts, args)
    else:
        icp_terms = (points, pose, np.dot(model_inverse, pose), mv, mn, camera, limits, robust)
        rgbd_terms = (columns, warp_terms, row_terms)
        corresponded[0] = 0
        args = (corresponded, icp_terms, icp_out, rgbd_terms, pairs, sums, warps, rgbd_out)
        if team == 1:
            _joint_loop(claims, parts, *args)
        else:
            failed = run_on_threads(team, _joint_loop, claims, parts, args)
    a, b, count, _ = _level_sums(kind, icp_out, sums, rgbd_out, weights, pose[:3, 3].copy())
    return failed, a, b, count


# ----------------------------------------------------------------------------------------------
# Host side


class JointLevel:
    """What every iteration at one level passes the joint loop: the ICP problem's points, model
    maps and camera, the RGB-D problem's level terms, and the work arrays both write, made once
    for all of the level's iterations. Either problem may be None (the other's system alone,
    `kind` ICP_ONLY or RGBD_ONLY): its terms then have no points and the types of a frame's
    (`_no_icp`, `_no_rgbd`), so that one compiled level serves all three kinds. The RGB-D
    problem alone runs its own two-pass loop (rgbd/cpu.py's _rgbd_system_loop): through the
    joint loop it took 20-60 microseconds a step longer (docs/benchmarks.md)."""

    def __init__(self, icp, rgbd, level: int) -> None:  # noqa: ANN001 (the CPU's problems)
        self.level = level  # named in benchmarks/warm_profile.py's per-level loop times
        # Held weakly: the ICP problem keeps its levels (joint_level), and a reference back
        # would make a cycle that only Python's cyclic collector frees, so that every frame's
        # problems and arrays (about 40 MB at 640x480) would stay until it ran, each frame's
        # on fresh pages (docs/benchmarks.md).
        self.icp = None if icp is None else weakref.proxy(icp)
        self.kind = RGBD_ONLY if icp is None else ICP_ONLY if rgbd is None else JOINT
        self.loop = _rgbd_system_loop if icp is None else _joint_loop
        icp_terms = _icp_terms(icp, level) if icp is not None else _no_icp()
        self.points, self.model, limits, robust, model_inverse = icp_terms
        levels = icp.current_levels if icp is not None else rgbd.previous_levels
        self.camera = pinhole(levels[level].camera)
        rgbd_terms = rgbd.level_terms(level) if rgbd is not None else _no_rgbd(self.camera)
        self.columns, self.warp_terms, self.row_terms = rgbd_terms
        self.icp_out = partials(self.points.shape[1])
        interest = self.columns[0].shape[1]
        self.pairs, self.sums, self.warps = _work(interest)
        self.rgbd_out = partials(interest)
        joint_parts = self.icp_out.shape[0] + 2 * self.sums.shape[0]
        self.parts = _two_pass_parts() if self.kind == RGBD_ONLY else joint_parts
        self.corresponded = np.zeros(1, dtype=np.int64)
        self.items = self.points.shape[1] + interest
        # what _refine_level reads, made once per level
        warp = self.warp_terms
        self.fixed = (
            (self.points, *self.model, self.camera, limits, robust),
            np.ascontiguousarray(model_inverse, dtype=np.float64),
            self.columns,
            (warp.to_previous, warp.images, warp.warped, warp.intrinsics, warp.max_change),
            self.row_terms,
        )
        arrays = (self.corresponded, self.icp_out, self.pairs, self.sums, self.warps)
        self.work = (*arrays, self.rgbd_out, self.parts)
        self.steps = 0

    def arguments(self, pose: np.ndarray) -> tuple:
        """_joint_loop's arguments after (claims, parts) at `pose`, of the joint kind; its
        count of correspondence chunks done, `corresponded`, is zeroed before each call."""
        pose, to_model, dist2, cos_min = self.icp.constants(pose)
        limits = (dist2, cos_min)
        icp_terms = (self.points, pose, to_model, *self.model, self.camera, limits, self.icp.robust)
        rgbd_terms = (self.columns, self.warp_terms(pose), self.row_terms)
        work = (self.pairs, self.sums, self.warps, self.rgbd_out)
        return (self.corresponded, icp_terms, self.icp_out, rgbd_terms, *work)

    def system(self, pose: np.ndarray, rgbd_weight: float, threshold: float) -> LinearSystem:
        """The joint system at `pose` (combined.joint_system's degeneracy-aware branch)."""
        arguments = self.arguments(pose)
        self.corresponded[0] = 0
        run_parallel(_joint_loop, *arguments, parts=self.parts, items=self.items)
        centre = np.ascontiguousarray(np.asarray(pose, dtype=np.float64)[:3, 3])
        a, b, count, cost = _joint_sums(
            self.icp_out,
            self.sums,
            self.rgbd_out,
            float(rgbd_weight),
            centre,
            float(threshold),
        )
        return LinearSystem(a, b, count, cost)

    def refine(
        self,
        pose: np.ndarray,
        steps: int,
        min_count: int,
        converged: float,
        weights: tuple[float, float],
    ) -> tuple[np.ndarray, str] | None:
        """solve.refine over this level alone, every step compiled (_refine_level): (pose, '')
        or (pose so far, why its step failed); `weights` = (rgbd_weight, degeneracy threshold).
        None where the loop would run on the helper team, which only Python joins. The systems
        computed (the steps taken and a failed one) are kept in `self.steps`."""
        team, native = planned_team(self.loop, self.items)
        team = min(team, self.parts)
        if team > 1 and not native:
            return None
        start_numba_threads()
        started = time.perf_counter()
        pose, status, condition, count, self.steps = _refine_level(
            self.kind,
            team,
            steps,
            min_count,
            float(converged),
            np.array(pose, dtype=np.float64),
            self.fixed,
            self.work,
            (float(weights[0]), float(weights[1])),
        )
        seconds = (time.perf_counter() - started) / max(self.steps, 1)
        LOOP_COSTS.record(self.loop, self.items, seconds * team)
        if status == THREAD_FAILED:
            raise RuntimeError("a cpu loop failed on one of its threads; run it on one to see why")
        if status != SOLVED:
            return pose, failure_reason(status, condition, count, min_count)
        return pose, ""


def joint_level(icp, rgbd, level: int) -> JointLevel:  # noqa: ANN001 (the CPU's problems)
    """The JointLevel of `icp` and `rgbd` (either may be None: the other's system alone) at
    `level`, made on first use and kept on the ICP problem, or on the RGB-D problem alone."""
    owner = icp if icp is not None else rgbd
    levels: dict[tuple, JointLevel] = owner.__dict__.setdefault("_joint_levels", {})
    key = (level, icp is None, rgbd is None)
    if key not in levels:
        levels[key] = JointLevel(icp, rgbd, level)
    return levels[key]


def _icp_terms(icp, level: int) -> tuple:  # noqa: ANN001 (the CPU's IcpProblem)
    """(points, model maps, limits, robust terms, model inverse) of the ICP problem at `level`;
    the pair tests' limits are the same at every pose."""
    limits = icp.constants(np.eye(4))[2:]
    return icp.points(level), icp.model(level), limits, icp.robust, icp.model_inverse


def _no_icp() -> tuple:
    """_icp_terms of an ICP part without points, typed as a frame's: float32 columns and maps,
    least squares."""
    maps = (np.zeros((1, 1, 3), np.float32), np.zeros((1, 1, 3), np.float32))
    return np.zeros((6, 0), np.float32), maps, (0.0, 1.0), NO_WEIGHTS, np.eye(4)


def _no_rgbd(intrinsics: tuple) -> tuple:
    """(columns, WarpTerms, row terms) of an RGB-D part without interest points, typed as a
    frame's: float64 columns, float32 images."""
    columns = (np.zeros((3, 0)), np.zeros(0), np.zeros((2, 0)))
    images = tuple(np.zeros((1, 1), np.float32) for _ in range(4))
    warp = WarpTerms(np.eye(4), images, False, intrinsics, 0.0)
    return columns, warp, (np.eye(4), (1.0, 1.0))


def joint_system(
    icp,  # noqa: ANN001 (the CPU's IcpProblem)
    rgbd,  # noqa: ANN001 (the CPU's RgbdProblem)
    level: int,
    pose: np.ndarray,
    rgbd_weight: float,
    threshold: float,
) -> LinearSystem:
    """combined.joint_system(icp.system(level, pose), rgbd.system(level, pose), rgbd_weight,
    a degeneracy-aware weighting, camera position pose[:3, 3], threshold), computed in one
    parallel call and one compiled function; the level's JointLevel is kept on `icp`."""
    return joint_level(icp, rgbd, level).system(pose, rgbd_weight, threshold)
