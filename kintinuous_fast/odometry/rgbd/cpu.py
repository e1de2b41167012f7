# ruff: noqa: ANN001, ANN201  (numba loops: argument types come from the call)
"""kintinuous_ref.odometry.rgbd on the CPU: loops on all threads around rgbd/ops.py.

Same public names, signatures and results as the reference module (tests/test_fast_odometry.py
states the tolerances; the names it does not compute itself are the reference's own objects).
An iteration's system takes two passes over the interest points, in one parallel call: the
correspondences and their sum of r^2 (sigma'), then, once every chunk's sum is in, the robustly
weighted rows summed block by block into fixed-chunk partial sums (odometry/sums/cpu.py). Lists
come out in the reference's order.
"""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np

from kintinuous_fast.odometry import check_image
from kintinuous_fast.odometry.sums import NV, chunks_for, sum_partials
from kintinuous_fast.odometry.sums.cpu import (
    ALLOCATING_LOOP,
    BLOCK,
    CHUNKS,
    GEOMETRY,
    INLINE,
    LOOP,
    add_block,
    partials,
    row_starts,
    run,
    stage,
)
from kintinuous_fast.targets import pinhole
from kintinuous_fast.targets.cpu import (
    PARTS_PER_THREAD,
    SPINS,
    claim_slot,
    claimed_items,
    claimed_items_in_passes,
    run_parallel,
    threads,
)
from kintinuous_ref.camera import Intrinsics
from kintinuous_ref.odometry import rgbd as reference
from kintinuous_ref.odometry.rgbd import Correspondences, InterestPoints
from kintinuous_ref.odometry.rgbd import check_gradient as check_gradient
from kintinuous_ref.odometry.rgbd import photometric_residuals as photometric_residuals
from kintinuous_ref.odometry.rgbd import robust_row_weights as robust_row_weights
from kintinuous_ref.odometry.rgbd import sample_bilinear as sample_bilinear
from kintinuous_ref.odometry.solve import LinearSystem

from . import REFERENCE_NAMES, TARGET_NAMES, check_images
from .ops import build_ops

# The reference's own objects (REFERENCE_NAMES) and what this target computes (TARGET_NAMES),
# listed in rgbd/__init__.py.
__all__ = [*REFERENCE_NAMES, *TARGET_NAMES]

_ops = build_ops(INLINE, GEOMETRY)
# Module-level names: numba resolves the scalar functions as globals of the loops below.
_is_interest = _ops.is_interest
_has_depth = _ops.has_depth
_backproject = _ops.backproject
_warp_project = _ops.warp_project
_warp_sample = _ops.warp_sample
_photometric_row = _ops.photometric_row
_robust_weight = _ops.robust_weight


# ----------------------------------------------------------------------------------------------
# Loops


@LOOP
def _gradient_mask_loop(claims, parts, dx, dy, g2, mask):
    """mask[v, u] = Algorithm 1's gradient test, for the rows this thread claims."""
    for v in claimed_items(claims, dx.shape[0], parts):
        for u in range(dx.shape[1]):
            mask[v, u] = _is_interest(dx, dy, v, u, g2)


@INLINE
def _is_interest_point(dx, dy, depth, v, u, g2, max_depth):
    """prepare_level's test of pixel (v, u): Algorithm 1's gradient test, then valid depth."""
    return _is_interest(dx, dy, v, u, g2) and _has_depth(depth, v, u, max_depth)


@LOOP
def _interest_counts_loop(claims, parts, dx, dy, depth, g2, max_depth, counts):
    """counts[v] = the interest points of row v (_is_interest_point)."""
    for v in claimed_items(claims, dx.shape[0], parts):
        count = 0
        for u in range(dx.shape[1]):
            count += _is_interest_point(dx, dy, depth, v, u, g2, max_depth)
        counts[v] = count


@LOOP
def _interest_rows_loop(claims, parts, starts, images, g2, max_depth, camera, out):
    """The interest points of each row v this thread claims, from column starts[v] of `out` =
    (flat indices, 3D points, intensities, gradients), in row-major order: what np.flatnonzero
    of their mask and a gather at those indices give, read row by row. `images` = (depth,
    intensity, dx, dy)."""
    depth, intensity, dx, dy = images
    indices, points, values, grad = out
    width = depth.shape[1]
    for v in claimed_items(claims, depth.shape[0], parts):
        k = starts[v]
        for u in range(width):
            if _is_interest_point(dx, dy, depth, v, u, g2, max_depth):
                indices[k] = v * width + u
                x, y, z = _backproject(u, v, float(depth[v, u]), camera)
                points[0, k], points[1, k], points[2, k] = x, y, z
                values[k] = float(intensity[v, u])
                grad[0, k] = float(dx[v, u])
                grad[1, k] = float(dy[v, u])
                k += 1


@numba.njit(cache=True, error_model="numpy")
def _warp_block(points, start, stop, relative, camera, warp):
    """_warp_project of points start:stop into warp's columns (x, y, z, u, v): branch-free, so
    it vectorises (divisions 8 at a time; rows read as slices, see icp/cpu.py's _project_block)."""
    px, py, pz = points[0, start:stop], points[1, start:stop], points[2, start:stop]
    for i in range(stop - start):
        x, y, z, u, v = _warp_project(relative, (px[i], py[i], pz[i]), camera)
        warp[0, i], warp[1, i], warp[2, i], warp[3, i], warp[4, i] = x, y, z, u, v


@LOOP  # compiled as the loops are: no reference counts around its accesses
def _correspond_chunk(c, points, intensity, gradient, warp_terms, pairs, sums, warp):
    """Algorithm 2 for chunk c of the interest points (of sums.shape[0]): pairs[:, k] =
    (residual, NaN = not kept; world point; warped point; gradient), what J needs, and sums[c] =
    (sum r^2, count) for sigma'. Each block's warps first, in a loop that vectorises;
    `warp_terms` = (relative, pose, previous, warped, camera, max_change), `previous` = the
    (depth, intensity, dx, dy) images of the previous frame; `warp` this thread's work array.
    The sums are kept in registers and stored once: four chunks' sums share a cache line, and a
    store per pair, with another thread storing into the chunk beside, slowed these chunks on
    two threads by 20-30 % more than the ICP chunks of the same calls."""
    relative, pose, previous, warped, camera, max_change = warp_terms
    depth, prev_i, prev_dx, prev_dy = previous
    n = pairs.shape[1]
    chunks = sums.shape[0]
    start, stop = c * n // chunks, (c + 1) * n // chunks
    squares, count = 0.0, 0.0
    for block in range(start, stop, BLOCK):
        end = min(block + BLOCK, stop)
        _warp_block(points, block, end, relative, camera, warp)
        for k in range(block, end):
            i = k - block
            sample = (warp[0, i], warp[1, i], warp[2, i], warp[3, i], warp[4, i])
            ok, r, wx, wy, wz, x, y, z, gx, gy = _warp_sample(
                points,
                intensity,
                gradient,
                k,
                sample,
                pose,
                depth,
                prev_i,
                prev_dx,
                prev_dy,
                warped,
                max_change,
            )
            pairs[0, k], pairs[1, k], pairs[2, k], pairs[3, k] = r, wx, wy, wz
            pairs[4, k], pairs[5, k], pairs[6, k] = x, y, z
            pairs[7, k], pairs[8, k] = gx, gy
            if ok:
                squares += r * r
                count += 1.0
    sums[c, 0], sums[c, 1] = squares, count


@LOOP
def _correspond_loop(claims, parts, points, intensity, gradient, warp_terms, pairs, sums, warps):
    """_correspond_chunk of every chunk; `warps` (threads, 5, BLOCK): each thread's work
    array."""
    warp = warps[claim_slot(claims)]
    for c in claimed_items(claims, sums.shape[0], parts):
        _correspond_chunk(c, points, intensity, gradient, warp_terms, pairs, sums, warp)


@LOOP
def _photometric_loop(
    claims, parts, world, warped_points, gradient, previous_pose, focal, jacobian
):
    for k in claimed_items(claims, world.shape[1], parts):
        j0, j1, j2, j3, j4, j5 = _photometric_row(
            (world[0, k], world[1, k], world[2, k]),
            (warped_points[0, k], warped_points[1, k], warped_points[2, k]),
            (gradient[0, k], gradient[1, k]),
            previous_pose,
            focal,
        )
        jacobian[0, k], jacobian[1, k], jacobian[2, k] = j0, j1, j2
        jacobian[3, k], jacobian[4, k], jacobian[5, k] = j3, j4, j5


@numba.njit(cache=True, error_model="numpy")
def _weighted_rows_block(pairs, start, stop, previous_pose, focal, sigma, rows):
    """_photometric_row and the squared robust weight w of pairs[:, start:stop] (_correspond_loop's
    columns), branch-free so that it vectorises: rows[k * BLOCK + m] = (j0..j5, r, 1) for
    k = 0..7 and (w j0..w j5, w r) for k = 8..14 of a kept pair, zeros for a pair not kept (NaN
    r). rows is flat: with constant offsets LLVM sees one output region (a (7, BLOCK) array's 7
    rows are too many overlap checks for it)."""
    # the rows as slices indexed from 0 (see icp/cpu.py's _project_block)
    r, wx, wy = pairs[0, start:stop], pairs[1, start:stop], pairs[2, start:stop]
    wz, x, y = pairs[3, start:stop], pairs[4, start:stop], pairs[5, start:stop]
    z, gx, gy = pairs[6, start:stop], pairs[7, start:stop], pairs[8, start:stop]
    for i in range(stop - start):
        j0, j1, j2, j3, j4, j5 = _photometric_row(
            (wx[i], wy[i], wz[i]), (x[i], y[i], z[i]), (gx[i], gy[i]), previous_pose, focal
        )
        kept = not np.isnan(r[i])
        w = _robust_weight(r[i], sigma)
        w = w * w
        residual = r[i] if kept else 0.0
        j0, j1, j2 = (j0, j1, j2) if kept else (0.0, 0.0, 0.0)
        j3, j4, j5 = (j3, j4, j5) if kept else (0.0, 0.0, 0.0)
        rows[i], rows[BLOCK + i], rows[2 * BLOCK + i] = j0, j1, j2
        rows[3 * BLOCK + i], rows[4 * BLOCK + i], rows[5 * BLOCK + i] = j3, j4, j5
        rows[6 * BLOCK + i], rows[7 * BLOCK + i] = residual, 1.0 if kept else 0.0
        rows[8 * BLOCK + i], rows[9 * BLOCK + i], rows[10 * BLOCK + i] = w * j0, w * j1, w * j2
        rows[11 * BLOCK + i], rows[12 * BLOCK + i] = w * j3, w * j4
        rows[13 * BLOCK + i], rows[14 * BLOCK + i] = w * j5, w * residual


@ALLOCATING_LOOP
def _rows_chunk(c, pairs, previous_pose, focal, sigma, out):
    """out[c] = the robustly weighted photometric rows of chunk c's kept pairs (of
    out.shape[0]), summed block by block: the rows, then their sums, each in a loop that
    vectorises."""
    n = pairs.shape[1]
    chunks = out.shape[0]
    acc = np.zeros(NV)
    rows = np.empty(15 * BLOCK)
    matrix = rows.reshape((15, BLOCK))
    start, stop = c * n // chunks, (c + 1) * n // chunks
    for block in range(start, stop, BLOCK):
        end = min(block + BLOCK, stop)
        _weighted_rows_block(pairs, block, end, previous_pose, focal, sigma, rows)
        add_block(acc, matrix[8:], matrix[:8], end - block)
    out[c] = acc


@numba.njit(cache=True)
def _robust_scale(sums):
    """(whether there are pairs, sigma') from the first pass's per-chunk (sum r^2, count),
    added in chunk order; sigma' 0 without pairs (no rows: the host returns an empty
    system)."""
    squares, count = 0.0, 0.0
    for c in range(sums.shape[0]):
        squares += sums[c, 0]
        count += sums[c, 1]
    has_pairs = count > 0.0
    return has_pairs, np.sqrt(squares / count) if has_pairs else 0.0


@ALLOCATING_LOOP
def _rgbd_system_loop(
    claims, parts, points, intensity, gradient, warp_terms, row_terms, pairs, sums, warps, out
):
    """One iteration's system in one call, its `parts` (even) half for each pass: items
    0..chunks-1 are _correspond_chunk's chunks, chunks..2 chunks-1 _rows_chunk's, the second
    pass's parts claimed once the first's are done (claimed_items_in_passes). A thread's first
    chunk of the second pass takes sigma' from the first pass's sums added in chunk order.
    `row_terms` = (previous pose, focal). The two passes share one wake-up of the threads and
    no Python between them; the call returns once every part of both is done."""
    previous_pose, focal = row_terms
    chunks = sums.shape[0]
    warp = warps[claim_slot(claims)]
    sigma, has_pairs = -1.0, False
    for item in claimed_items_in_passes(claims, 2 * chunks, parts, parts // 2, SPINS):
        if item < chunks:
            _correspond_chunk(item, points, intensity, gradient, warp_terms, pairs, sums, warp)
            continue
        if sigma < 0.0:  # this thread's first chunk of the second pass
            has_pairs, sigma = _robust_scale(sums)
        if has_pairs:
            _rows_chunk(item - chunks, pairs, previous_pose, focal, sigma, out)


# ----------------------------------------------------------------------------------------------
# Host side


def interest_points(
    intensity_dx: np.ndarray, intensity_dy: np.ndarray, min_gradient: float
) -> np.ndarray:
    """Algorithm 1: flat indices (ascending) of the pixels with dx^2 + dy^2 >= g^2."""
    dx, dy = stage(intensity_dx), stage(intensity_dy)
    check_image("intensity_dy", dy, dx.shape)
    mask = np.empty(dx.shape, dtype=np.bool_)
    run(_gradient_mask_loop, dx.size, dx, dy, float(min_gradient) ** 2, mask)
    return np.flatnonzero(mask)


def prepare_level(
    depth: np.ndarray,
    intensity: np.ndarray,
    intensity_dx: np.ndarray,
    intensity_dy: np.ndarray,
    camera: Intrinsics,
    min_gradient: float,
    max_depth: float,
) -> InterestPoints:
    """Interest points with valid depth and their 3D points, intensities and gradients: counted
    row by row, then written row by row from each row's first column (no mask image, no
    gather at scattered indices)."""
    depth, intensity = stage(depth), stage(intensity)
    dx, dy = stage(intensity_dx), stage(intensity_dy)
    check_images("current", camera, depth=depth, intensity=intensity, dx=dx, dy=dy)
    tests = (float(min_gradient) ** 2, float(max_depth))
    counts = np.empty(depth.shape[0], dtype=np.int64)
    run(_interest_counts_loop, depth.size, dx, dy, depth, *tests, counts)
    starts, n = row_starts(counts)
    out = (np.empty(n, dtype=np.intp), np.empty((3, n)), np.empty(n), np.empty((2, n)))
    images = (depth, intensity, dx, dy)
    run(_interest_rows_loop, depth.size, starts, images, *tests, pinhole(camera), out)
    return InterestPoints(*out)


def _previous_images(depth, intensity, dx, dy, camera) -> tuple[tuple, bool]:
    """The previous frame's (depth, intensity, dx, dy) as _correspond_loop reads them, checked,
    and whether the gradients are the previous image's ("warped" mode; without them the
    intensity stands in for dx and dy, unread)."""
    depth, intensity = stage(depth), stage(intensity)
    check_images("previous", camera, depth=depth, intensity=intensity)
    warped = dx is not None and dy is not None
    dx = stage(dx) if warped else intensity
    dy = stage(dy) if warped else intensity
    return (depth, intensity, dx, dy), warped


def _point_columns(points: InterestPoints) -> tuple:
    """The interest points' (points, intensity, gradient) as the loops read them."""
    return (
        np.ascontiguousarray(points.points, dtype=np.float64),
        np.ascontiguousarray(points.intensity, dtype=np.float64),
        np.ascontiguousarray(points.gradient, dtype=np.float64),
    )


@dataclass(frozen=True)
class WarpTerms:
    """What _correspond_chunk's warp terms hold at every iteration of a level, and, called with
    a pose, the terms themselves: (relative pose, pose, images, warped, intrinsics, max
    change). `to_previous` is relative_pose's inverse, computed once per level; `images` the
    previous frame's (depth, intensity, dx, dy) as _previous_images stages them."""

    to_previous: np.ndarray
    images: tuple
    warped: bool
    intrinsics: tuple
    max_change: float

    def __call__(self, pose: np.ndarray) -> tuple:
        relative = np.ascontiguousarray(self.to_previous @ pose, dtype=np.float64)
        pose = np.ascontiguousarray(pose, dtype=np.float64)
        return (relative, pose, self.images, self.warped, self.intrinsics, self.max_change)


def _level_terms(points, previous_pose, previous, camera, max_depth_change) -> tuple:
    """What every iteration at a level passes the loops, made once per level: the interest
    points' columns (_point_columns) and the WarpTerms of _correspond_chunk; `previous` = the
    previous frame's (depth, intensity, dx, dy), dx and dy None but in "warped" mode."""
    images, warped = _previous_images(*previous, camera)
    to_previous = np.ascontiguousarray(np.linalg.inv(previous_pose), dtype=np.float64)
    terms = WarpTerms(to_previous, images, warped, pinhole(camera), float(max_depth_change))
    return _point_columns(points), terms


def _focal(camera: Intrinsics) -> tuple[float, float]:
    return (float(camera.fx), float(camera.fy))


def _work(n: int) -> tuple:
    """A pass's outputs over n interest points: (9, n) pairs, per-chunk (sum r^2, count) and
    each thread's warp work array."""
    return np.empty((9, n)), np.zeros((chunks_for(n, CHUNKS), 2)), np.empty((threads(), 5, BLOCK))


def _correspond_all(points, pose, previous_pose, previous, camera, max_depth_change):
    """Per interest point: ((9, n) pairs as _correspond_chunk writes them, (sum r^2, count));
    `previous` = the previous frame's (depth, intensity, dx, dy), dx and dy None but in
    "warped" mode."""
    columns, warp_terms = _level_terms(points, previous_pose, previous, camera, max_depth_change)
    n = columns[0].shape[1]
    pairs, sums, warps = _work(n)
    run(_correspond_loop, n, *columns, warp_terms(pose), pairs, sums, warps)
    return pairs, sums.sum(axis=0)


def _two_pass_parts() -> int:
    """The parts of one _rgbd_system_loop call: PARTS_PER_THREAD per thread for each pass."""
    return 2 * PARTS_PER_THREAD * threads()


def _system(columns, terms, previous_pose, focal) -> LinearSystem:
    """rgbd_system of the interest points' `columns` (_point_columns) and warp `terms`
    (_correspond_chunk's): both passes in one call of _rgbd_system_loop."""
    n = columns[0].shape[1]
    pairs, sums, warps = _work(n)
    out = partials(n)
    both_passes = _two_pass_parts()
    arguments = (*columns, terms, (previous_pose, focal), pairs, sums, warps, out)
    run_parallel(_rgbd_system_loop, *arguments, parts=both_passes, items=n)
    if sums.sum(axis=0)[1] == 0:
        return LinearSystem.empty()
    return sum_partials(out)[0]


def correspond(
    points: InterestPoints,
    pose: np.ndarray,
    previous_pose: np.ndarray,
    previous_depth: np.ndarray,
    previous_intensity: np.ndarray,
    camera: Intrinsics,
    max_depth_change: float,
    previous_dx: np.ndarray | None = None,
    previous_dy: np.ndarray | None = None,
) -> Correspondences:
    """Algorithm 2: the interest points warped into the previous frame (eq. 2) that pass the
    image and d_s tests, in the reference's order."""
    previous = (previous_depth, previous_intensity, previous_dx, previous_dy)
    pairs, _ = _correspond_all(points, pose, previous_pose, previous, camera, max_depth_change)
    kept = np.flatnonzero(~np.isnan(pairs[0]))
    columns = np.take(pairs, kept, axis=1)
    return Correspondences(
        np.ascontiguousarray(columns[1:4]),
        np.ascontiguousarray(columns[4:7]),
        columns[0].copy(),
        np.ascontiguousarray(columns[7:9]),
        kept,
    )


def photometric_rows(
    correspondences: Correspondences, previous_pose: np.ndarray, camera: Intrinsics
) -> tuple[np.ndarray, np.ndarray]:
    """Unweighted Jacobian (6, N) and residuals (N,) of the intensity differences at xi = 0."""
    n = correspondences.world.shape[1]
    jacobian = np.empty((6, n))
    run(
        _photometric_loop,
        n,
        np.ascontiguousarray(correspondences.world, dtype=np.float64),
        np.ascontiguousarray(correspondences.warped, dtype=np.float64),
        np.ascontiguousarray(correspondences.gradient, dtype=np.float64),
        np.ascontiguousarray(previous_pose, dtype=np.float64),
        (float(camera.fx), float(camera.fy)),
        jacobian,
    )
    return jacobian, correspondences.residuals


def rgbd_system(
    points: InterestPoints,
    pose: np.ndarray,
    previous_pose: np.ndarray,
    previous_depth: np.ndarray,
    previous_intensity: np.ndarray,
    camera: Intrinsics,
    max_depth_change: float = 0.07,
    previous_dx: np.ndarray | None = None,
    previous_dy: np.ndarray | None = None,
) -> LinearSystem:
    """The 6x6 normal equations of one RGB-D iteration at one level, robustly weighted: pass 1
    finds the pairs and sum r^2 (sigma'), pass 2 sums the weighted rows."""
    previous = (previous_depth, previous_intensity, previous_dx, previous_dy)
    arguments = (points, previous_pose, previous, camera, max_depth_change)
    columns, warp_terms = _level_terms(*arguments)
    row_terms = (np.ascontiguousarray(previous_pose, dtype=np.float64), _focal(camera))
    return _system(columns, warp_terms(pose), *row_terms)


class RgbdProblem(reference.RgbdProblem):
    """kintinuous_ref.odometry.rgbd.RgbdProblem with the CPU loops underneath; what a level's
    iterations share (the points' columns, the staged previous images) is made once per level."""

    stage = staticmethod(stage)
    prepare_level = staticmethod(prepare_level)
    rgbd_system = staticmethod(rgbd_system)

    def level_terms(self, level: int) -> tuple:
        """(columns, warp_terms, row_terms) of the level, what its iterations share: the interest
        points' columns (_point_columns), _correspond_chunk's WarpTerms (which give its warp
        terms at a pose) and (previous pose, focal); made once per level and kept on the problem,
        which keeps the reference's constructor."""
        levels: dict[int, tuple] = self.__dict__.setdefault("_levels", {})
        if level not in levels:
            camera = self.previous_levels[level].camera
            arguments = (self.previous_pose, self.previous(level), camera, self.max_depth_change)
            columns, warp_terms = _level_terms(self.points(level), *arguments)
            row_terms = (np.ascontiguousarray(self.previous_pose, dtype=np.float64), _focal(camera))
            levels[level] = (columns, warp_terms, row_terms)
        return levels[level]

    def system(self, level: int, pose: np.ndarray) -> LinearSystem:
        """rgbd_system of the level at `pose`, from the terms its iterations share."""
        columns, warp_terms, row_terms = self.level_terms(level)
        return _system(columns, warp_terms(pose), *row_terms)

    def refine_level(
        self, level: int, pose: np.ndarray, steps: int, min_count: int, converged: float
    ) -> tuple[np.ndarray, str] | None:
        """solve.refine's steps at one level over this problem's system, all in compiled code
        (JointLevel.refine, this module's two-pass loop): (pose, '') or (pose so far, why a
        step failed); None where the loop runs on the helper team, or where a subclass computes
        a `system` of its own."""
        if type(self).system is not RgbdProblem.system:
            return None
        # imported here: the joint loop's module imports this one
        from kintinuous_fast.odometry.icp.cpu_joint import joint_level

        level_terms = joint_level(None, self, level)
        return level_terms.refine(pose, steps, min_count, converged, (0.0, 0.0))

    def inlier_fraction(self, pose: np.ndarray, level: int = 0) -> float:
        """As the base class, from the correspondences alone (the first pass): the system's
        count is the number of pairs kept there, and its sums are not needed for one look."""
        columns, warp_terms, _ = self.level_terms(level)
        n = columns[0].shape[1]
        if n == 0:
            return 0.0
        pairs, sums, warps = _work(n)
        run(_correspond_loop, n, *columns, warp_terms(pose), pairs, sums, warps)
        return int(sums.sum(axis=0)[1]) / n
