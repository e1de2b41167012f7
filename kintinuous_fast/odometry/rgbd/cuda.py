# ruff: noqa: ANN001, ANN201  (numba kernels: argument types come from the call)
"""kintinuous_ref.odometry.rgbd as CUDA kernels around rgbd/ops.py, after the paper's GPU
design (section IV-A.2/3), whose Algorithms 1-2 list each kept item in a block's shared memory
and then copy it out with one global atomic per item:

- Algorithm 1 (interest points): each block collects its pixels that pass the gradient test in a
  shared-memory list (shared-memory atomics), then reserves room in the global list with ONE
  global atomic per block (not per item: atomics on one address serialise) and copies its list
  there.
- Algorithm 2 (correspondences): the same per-block shared list for the warped interest points
  that pass the image and d_s tests; the block adds its pairs' r^2 by a tree and makes one
  atomic for the global intensity-difference sum and one for its room in the global
  correspondence list (the printed algorithm makes one of each per pair).
- The robustly weighted rows of the listed pairs: per-thread sums reduced by a tree in shared
  memory per block (odometry/sums/cuda.py), one partial per block for the host to add.

Same public names, signatures and results as the reference module (the names it does not
compute itself are the reference's own objects), except that lists come out in atomic order:
compare interest points and correspondences as sets. Arrays stay where they are given
(kintinuous_fast.targets.cuda): device arrays in, device arrays out; NumPy in, NumPy out. Runs
on numba's CUDA simulator too.
"""

from __future__ import annotations

import math

import numpy as np
from numba import cuda, float64, int32, int64

from kintinuous_fast.odometry import check_image
from kintinuous_fast.odometry.sums import NV, sum_partials
from kintinuous_fast.odometry.sums.cuda import (
    ANY_LEVEL,
    BLOCK,
    DEVICE,
    GEOMETRY,
    add_row,
    block_reduce,
    counter,
    f64,
    gated,
    open_gate,
    reduction_blocks,
    rounded_up,
    scratch,
    stage,
    upload,
    zero,
)
from kintinuous_fast.targets import is_device, pinhole, to_host
from kintinuous_fast.targets.cuda import grid_1d, kernel, like_input
from kintinuous_ref.camera import Intrinsics
from kintinuous_ref.odometry import rgbd as reference
from kintinuous_ref.odometry.rgbd import Correspondences, InterestPoints
from kintinuous_ref.odometry.rgbd import check_gradient as check_gradient
from kintinuous_ref.odometry.rgbd import photometric_residuals as photometric_residuals
from kintinuous_ref.odometry.rgbd import robust_row_weights as robust_row_weights
from kintinuous_ref.odometry.rgbd import sample_bilinear as sample_bilinear
from kintinuous_ref.odometry.solve import LinearSystem

from . import REFERENCE_NAMES, TARGET_NAMES, check_images, relative_pose
from .ops import build_ops

# The reference's own objects (REFERENCE_NAMES) and what this target computes (TARGET_NAMES),
# listed in rgbd/__init__.py.
__all__ = [*REFERENCE_NAMES, *TARGET_NAMES]

_ops = build_ops(DEVICE, GEOMETRY)
# Module-level names: numba resolves the device functions as globals of the kernels below.
_is_interest = _ops.is_interest
_has_depth = _ops.has_depth
_backproject = _ops.backproject
_warp_point = _ops.warp_point
_photometric_row = _ops.photometric_row
_robust_weight = _ops.robust_weight

_EMPTY_TALLY = np.zeros(2)  # [pairs listed, sum of their r^2] before Algorithm 2


# ----------------------------------------------------------------------------------------------
# Kernels


@kernel
def interest_kernel(dx, dy, depth, g2, use_depth, max_depth, count, indices):
    """Algorithm 1: a shared-memory list per block, one global atomic per block that keeps a
    point (atomics on one address serialise, and most blocks of a frame keep none)."""
    local = cuda.shared.array(BLOCK, int64)
    local_count = cuda.shared.array(1, int32)
    base = cuda.shared.array(1, int32)
    t = cuda.threadIdx.x
    if t == 0:
        local_count[0] = 0
    cuda.syncthreads()
    width = dx.shape[1]
    i = cuda.grid(1)
    if i < dx.shape[0] * width:
        v = i // width
        u = i - v * width
        keep = _is_interest(dx, dy, v, u, g2)
        if keep and use_depth:
            keep = _has_depth(depth, v, u, max_depth)
        if keep:
            local[cuda.atomic.add(local_count, 0, 1)] = i
    cuda.syncthreads()
    if t == 0 and local_count[0] > 0:
        base[0] = cuda.atomic.add(count, 0, local_count[0])
    cuda.syncthreads()
    if t < local_count[0]:
        indices[base[0] + t] = local[t]


@kernel
def interest_data_kernel(indices, count, depth, intensity, dx, dy, camera, points, values, grad):
    k = cuda.grid(1)
    if k < count[0]:
        width = depth.shape[1]
        i = indices[k]
        v = i // width
        u = i - v * width
        x, y, z = _backproject(u, v, float(depth[v, u]), camera)
        points[0, k] = x
        points[1, k] = y
        points[2, k] = z
        values[k] = float(intensity[v, u])
        grad[0, k] = float(dx[v, u])
        grad[1, k] = float(dy[v, u])


@kernel
def correspond_kernel(
    points,
    count,
    intensity,
    gradient,
    poses,
    depth,
    prev_i,
    prev_dx,
    prev_dy,
    warped,
    camera,
    max_change,
    tally,
    pairs,
    gate,
    level,
):
    """Algorithm 2: kept pairs listed per block in shared memory with their r^2, the block's
    sum of r^2 added by a tree, then one atomic adds it to the global sum (tally[1]) and one
    takes the block's run of slots in the global list (counted in tally[0], a float64 that
    counts exactly to 2^53). Atomics on one address serialise: one per kept pair (tens of
    thousands an iteration) would cost more than the rest of the kernel; so a block that keeps
    no pair makes none, and a block past the interest points (most of a frame's grid, which
    has a thread per pixel) returns at once. `poses` = (relative, pose, previous) stacked;
    `count` = [interest points]; `gate`, `level`: sums.cuda.gated."""
    if gated(gate, level) or cuda.blockIdx.x * BLOCK >= count[0]:  # the whole block or none
        return
    relative, pose = poses[0], poses[1]
    local = cuda.shared.array(BLOCK, int64)
    local_r2 = cuda.shared.array(BLOCK, float64)
    local_count = cuda.shared.array(1, int32)
    base = cuda.shared.array(1, int64)
    t = cuda.threadIdx.x
    if t == 0:
        local_count[0] = 0
    cuda.syncthreads()
    k = cuda.grid(1)
    if k < count[0]:
        ok, r, wx, wy, wz, x, y, z, gx, gy = _warp_point(
            points,
            intensity,
            gradient,
            k,
            relative,
            pose,
            depth,
            prev_i,
            prev_dx,
            prev_dy,
            warped,
            camera,
            max_change,
        )
        if ok:
            slot = cuda.atomic.add(local_count, 0, 1)
            local[slot] = k
            local_r2[slot] = r * r
    cuda.syncthreads()
    kept = local_count[0]
    if t >= kept:
        local_r2[t] = 0.0  # the slots no pair took add nothing
    step = BLOCK // 2
    while step > 0:
        cuda.syncthreads()
        if t < step:
            local_r2[t] += local_r2[t + step]
        step //= 2
    if t == 0 and kept > 0:
        cuda.atomic.add(tally, 1, local_r2[0])
        base[0] = int(cuda.atomic.add(tally, 0, float(kept)))
    cuda.syncthreads()
    if t < kept:
        pairs[base[0] + t] = local[t]


@kernel
def _correspondence_data_kernel(
    pairs,
    n_pairs,
    points,
    count,
    intensity,
    gradient,
    poses,
    depth,
    prev_i,
    prev_dx,
    prev_dy,
    warped,
    camera,
    max_change,
    residuals,
    world,
    warped_points,
    used_gradient,
):
    relative, pose = poses[0], poses[1]
    j = cuda.grid(1)
    if j < n_pairs:
        ok, r, wx, wy, wz, x, y, z, gx, gy = _warp_point(
            points,
            intensity,
            gradient,
            pairs[j],
            relative,
            pose,
            depth,
            prev_i,
            prev_dx,
            prev_dy,
            warped,
            camera,
            max_change,
        )
        residuals[j] = r
        world[0, j], world[1, j], world[2, j] = wx, wy, wz
        warped_points[0, j], warped_points[1, j], warped_points[2, j] = x, y, z
        used_gradient[0, j], used_gradient[1, j] = gx, gy


@kernel
def rows_kernel(
    pairs,
    tally,
    points,
    count,
    intensity,
    gradient,
    poses,
    depth,
    prev_i,
    prev_dx,
    prev_dy,
    warped,
    camera,
    max_change,
    out,
    gate,
    level,
):
    """The robustly weighted photometric rows of the listed pairs, tree-reduced per block. The
    pair count and sum of r^2 are read from `tally` where correspond_kernel left them, so the
    host waits for neither: sigma' = sqrt(sum r^2 / count), as the host computed it. The grid
    has room for a pair per pixel; a block past the pairs writes its partial, zero, without
    the tree."""
    if gated(gate, level):
        return
    n_pairs = int(tally[0])
    if cuda.blockIdx.x * BLOCK >= n_pairs:  # no thread of the block has a pair
        if cuda.threadIdx.x < NV:
            out[cuda.blockIdx.x, cuda.threadIdx.x] = 0.0
        return
    shared = cuda.shared.array((NV, BLOCK), float64)
    acc = cuda.local.array(NV, float64)
    zero(acc)
    relative, pose, previous_pose = poses[0], poses[1], poses[2]
    sigma = math.sqrt(tally[1] / n_pairs) if n_pairs > 0 else 0.0
    for j in range(cuda.grid(1), n_pairs, cuda.gridsize(1)):
        ok, r, wx, wy, wz, x, y, z, gx, gy = _warp_point(
            points,
            intensity,
            gradient,
            pairs[j],
            relative,
            pose,
            depth,
            prev_i,
            prev_dx,
            prev_dy,
            warped,
            camera,
            max_change,
        )
        row = _photometric_row(
            (wx, wy, wz), (x, y, z), (gx, gy), previous_pose, (camera[0], camera[1])
        )
        w = _robust_weight(r, sigma)
        add_row(acc, row, r, w * w)
    block_reduce(acc, shared, out)


@kernel
def _photometric_kernel(world, warped_points, gradient, previous_pose, focal, jacobian):
    k = cuda.grid(1)
    if k < world.shape[1]:
        j0, j1, j2, j3, j4, j5 = _photometric_row(
            (world[0, k], world[1, k], world[2, k]),
            (warped_points[0, k], warped_points[1, k], warped_points[2, k]),
            (gradient[0, k], gradient[1, k]),
            previous_pose,
            focal,
        )
        jacobian[0, k], jacobian[1, k], jacobian[2, k] = j0, j1, j2
        jacobian[3, k], jacobian[4, k], jacobian[5, k] = j3, j4, j5


# ----------------------------------------------------------------------------------------------
# Host side


def _interest_list(dx, dy, depth, min_gradient: float, max_depth: float):
    """Algorithm 1 on the device: (indices device array, count)."""
    height, width = dx.shape
    n = height * width
    count = counter()
    indices = cuda.device_array(max(n, 1), dtype=np.int64)
    use_depth = depth is not None
    interest_kernel[grid_1d(n, BLOCK), BLOCK](
        dx,
        dy,
        depth if use_depth else dx,
        float(min_gradient) ** 2,
        use_depth,
        float(max_depth),
        count,
        indices,
    )
    total = int(to_host(count)[0])
    return indices[:total], total, count


def interest_points(intensity_dx, intensity_dy, min_gradient: float):
    """Algorithm 1: flat indices of the pixels with dx^2 + dy^2 >= g^2 (atomic order)."""
    check_image("intensity_dy", intensity_dy, intensity_dx.shape)
    indices, _, _ = _interest_list(stage(intensity_dx), stage(intensity_dy), None, min_gradient, 0)
    return like_input(indices, intensity_dx)


def prepare_level(
    depth,
    intensity,
    intensity_dx,
    intensity_dy,
    camera: Intrinsics,
    min_gradient: float,
    max_depth: float,
) -> InterestPoints:
    """Interest points with valid depth and their 3D points, intensities and gradients (on the
    device when `depth` is a device array)."""
    images = {"depth": depth, "intensity": intensity, "dx": intensity_dx, "dy": intensity_dy}
    check_images("current", camera, **images)
    d_depth, d_dx, d_dy = stage(depth), stage(intensity_dx), stage(intensity_dy)
    indices, n, count = _interest_list(d_dx, d_dy, d_depth, min_gradient, max_depth)
    size = max(n, 1)
    points = cuda.device_array((3, size), dtype=np.float64)
    values = cuda.device_array(size, dtype=np.float64)
    gradient = cuda.device_array((2, size), dtype=np.float64)
    if n:
        images = (indices, count, d_depth, stage(intensity), d_dx, d_dy)
        intrinsics = pinhole(camera)
        interest_data_kernel[grid_1d(n, BLOCK), BLOCK](
            *images, intrinsics, points, values, gradient
        )
    result = (indices, points[:, :n], values[:n], gradient[:, :n])
    if not is_device(depth):
        result = tuple(to_host(array) for array in result)
    return InterestPoints(*result)


def _pair_arguments(points, pose, previous_pose, previous, camera, max_depth_change) -> tuple:
    """The arguments _warp_point needs, on the device, in the kernels' order; `previous` = the
    previous frame's (depth, intensity, dx, dy), dx and dy None but in "warped" mode. The three
    poses (relative, current, previous) go up as one array, one copy per iteration."""
    check_images("previous", camera, depth=previous[0], intensity=previous[1])
    poses = (relative_pose(pose, previous_pose), pose, previous_pose)
    count = np.array([points.points.shape[1]], dtype=np.int32)
    interest = (f64(points.points), upload("rgbd point count", count))
    interest += (f64(points.intensity), f64(points.gradient))
    poses = upload("rgbd poses", np.stack(poses).astype(np.float64))
    return pair_arguments(interest, poses, previous, camera, max_depth_change)


def pair_arguments(interest: tuple, poses, previous: tuple, camera, max_depth_change) -> tuple:
    """What _warp_point reads, in the kernels' order: `interest` = the interest points' device
    (points, count, intensities, gradients), `poses` = (relative, current, previous) on the
    device, `previous` = the previous frame's (depth, intensity, dx, dy) staged here, dx and dy
    None but in "warped" mode."""
    previous_depth, previous_intensity, previous_dx, previous_dy = previous
    prev_i = stage(previous_intensity)
    warped = previous_dx is not None and previous_dy is not None
    return (
        *interest,
        poses,
        stage(previous_depth),
        prev_i,
        stage(previous_dx) if warped else prev_i,
        stage(previous_dy) if warped else prev_i,
        warped,
        pinhole(camera),
        float(max_depth_change),
    )


def _pair_list(arguments: tuple, n: int, pairs=None):
    """Algorithm 2 on the device: (pair list, tally = [count, sum of r^2]), both left there;
    `pairs`: the list's array (at least n long), else a new one."""
    tally = upload("rgbd tally", _EMPTY_TALLY)
    if pairs is None:
        pairs = cuda.device_array(max(n, 1), dtype=np.int64)
    if n:
        correspond_kernel[grid_1d(n, BLOCK), BLOCK](
            *arguments, tally, pairs, open_gate(), ANY_LEVEL
        )
    return pairs, tally


def correspond(
    points: InterestPoints,
    pose: np.ndarray,
    previous_pose: np.ndarray,
    previous_depth,
    previous_intensity,
    camera: Intrinsics,
    max_depth_change: float,
    previous_dx=None,
    previous_dy=None,
) -> Correspondences:
    """Algorithm 2: the interest points warped into the previous frame (eq. 2) that pass the
    image and d_s tests, in atomic order (`kept` says which interest point each pair is)."""
    previous = (previous_depth, previous_intensity, previous_dx, previous_dy)
    arguments = _pair_arguments(points, pose, previous_pose, previous, camera, max_depth_change)
    n = points.points.shape[1]
    pairs, tally = _pair_list(arguments, n)
    kept = int(to_host(tally)[0])
    size = max(kept, 1)
    residuals = cuda.device_array(size, dtype=np.float64)
    world = cuda.device_array((3, size), dtype=np.float64)
    warped_points = cuda.device_array((3, size), dtype=np.float64)
    gradient = cuda.device_array((2, size), dtype=np.float64)
    if kept:
        _correspondence_data_kernel[grid_1d(kept, BLOCK), BLOCK](
            pairs, kept, *arguments, residuals, world, warped_points, gradient
        )
    given = points.points
    return Correspondences(
        like_input(world[:, :kept], given),
        like_input(warped_points[:, :kept], given),
        like_input(residuals[:kept], given),
        like_input(gradient[:, :kept], given),
        like_input(pairs[:kept], given),
    )


def photometric_rows(
    correspondences: Correspondences, previous_pose: np.ndarray, camera: Intrinsics
) -> tuple:
    """Unweighted Jacobian (6, N) and residuals (N,) of the intensity differences at xi = 0."""
    n = correspondences.world.shape[1]
    if n == 0:
        return np.empty((6, 0)), correspondences.residuals
    jacobian = cuda.device_array((6, n), dtype=np.float64)
    _photometric_kernel[grid_1d(n, BLOCK), BLOCK](
        f64(correspondences.world),
        f64(correspondences.warped),
        f64(correspondences.gradient),
        cuda.to_device(np.ascontiguousarray(previous_pose, dtype=np.float64)),
        (float(camera.fx), float(camera.fy)),
        jacobian,
    )
    return like_input(jacobian, correspondences.world), correspondences.residuals


def rgbd_system(
    points: InterestPoints,
    pose: np.ndarray,
    previous_pose: np.ndarray,
    previous_depth,
    previous_intensity,
    camera: Intrinsics,
    max_depth_change: float = 0.07,
    previous_dx=None,
    previous_dy=None,
) -> LinearSystem:
    """The 6x6 normal equations of one RGB-D iteration at one level, robustly weighted:
    Algorithm 2 (list + sum r^2 by atomics), then sigma' and the weighted rows of the listed
    pairs tree-reduced per block; the host waits only for the block partials."""
    previous = (previous_depth, previous_intensity, previous_dx, previous_dy)
    arguments = _pair_arguments(points, pose, previous_pose, previous, camera, max_depth_change)
    n = points.points.shape[1]
    if n == 0:
        return LinearSystem.empty()
    pairs = scratch("rgbd pairs", (rounded_up(n),), np.int64)
    pairs, tally = _pair_list(arguments, n, pairs)
    # enough blocks for every interest point kept: no count to wait for
    blocks = rounded_up(reduction_blocks(n))
    out = scratch("rgbd partials", (blocks, NV))
    rows_kernel[blocks, BLOCK](pairs, tally, *arguments, out, open_gate(), ANY_LEVEL)
    return sum_partials(to_host(out))[0]


class RgbdProblem(reference.RgbdProblem):
    """kintinuous_ref.odometry.rgbd.RgbdProblem with the CUDA kernels underneath (the images are
    uploaded once per frame and level, and the interest points stay on the device for all
    iterations)."""

    stage = staticmethod(stage)
    prepare_level = staticmethod(prepare_level)
    rgbd_system = staticmethod(rgbd_system)
