# ruff: noqa: ANN001, ANN201  (numba kernels: argument types come from the call)
"""kintinuous_ref.odometry as CUDA kernels around kintinuous_fast.odometry.ops, following the
paper's GPU design (section IV-A.2/3, V-B):

- Algorithm 1 (interest points): each block collects its pixels that pass the gradient test in a
  shared-memory list (shared-memory atomics), then reserves room in the global list with ONE
  global atomic per block and copies its list there.
- Algorithm 2 (correspondences): the same per-block shared list for the warped interest points
  that pass the image and d_s tests; each listed pair then adds r^2 to the global
  intensity-difference sum and takes its slot in the global correspondence list with atomics.
- The normal equations: every thread sums its rows (grid-stride loop) into a local vector of
  21 + 6 numbers (upper triangle of J^T W J, J^T W r) plus cost and count, the block reduces the
  vectors by a tree in shared memory, one partial per block goes to global memory, the host
  adds the partials in float64 and solves the 6x6 system by Cholesky (kintinuous_ref's solve).

Same names, signatures and results as the reference (tests/test_fast_odometry*.py state the
tolerances), except that lists come out in atomic order: compare interest points and
correspondences as sets. Arrays stay where they are given (kintinuous_fast.targets.cuda):
device arrays in, device arrays out; NumPy in, NumPy out. Runs on numba's CUDA simulator too
(slowly).
"""

from __future__ import annotations

import math
import sys
from typing import Any

import numpy as np
from numba import cuda, float64, int32, int64

from kintinuous_fast.odometry import host
from kintinuous_fast.preprocess.cuda import model_pyramid
from kintinuous_fast.targets import cuda_device_jit, pinhole
from kintinuous_fast.targets.cuda import (
    BLOCK_1D,
    BLOCK_2D,
    grid_1d,
    grid_2d,
    is_device,
    like_input,
    to_device,
)
from kintinuous_ref.camera import Intrinsics
from kintinuous_ref.config import Config, IcpConfig
from kintinuous_ref.odometry import METHODS, Tracker, TrackingResult
from kintinuous_ref.odometry import repeated_streams as ref_repeated_streams
from kintinuous_ref.odometry.combined import icp_scale
from kintinuous_ref.odometry.icp import robust_threshold
from kintinuous_ref.odometry.rgbd import Correspondences, InterestPoints
from kintinuous_ref.odometry.solve import LinearSystem

from .ops import NV, build_ops
from .solve import CombinedProblem, apply_increment, joint_system, refine, solve

__all__ = [
    "METHODS",
    "CombinedProblem",
    "DenseTracker",
    "TrackingResult",
    "Correspondences",
    "IcpProblem",
    "InterestPoints",
    "LinearSystem",
    "RgbdProblem",
    "accumulate",
    "apply_increment",
    "associate",
    "correspond",
    "icp_scale",
    "icp_system",
    "interest_points",
    "joint_system",
    "make_tracker",
    "model_pyramid",
    "photometric_rows",
    "point_to_plane_rows",
    "prepare_level",
    "refine",
    "repeated_streams",
    "rgbd_system",
    "solve",
]

# Blocks of the reduction kernels at most (each thread then loops over several rows): enough to
# fill a GPU, few enough that the host adds the partials in microseconds.
MAX_BLOCKS = 1024
BLOCK = BLOCK_1D  # threads per block of every kernel here (a power of two: the tree halves it)

_ops = build_ops(cuda_device_jit())
icp_match = _ops.icp_match
map_point = _ops.map_point
point_to_plane_row = _ops.point_to_plane_row
is_interest = _ops.is_interest
has_depth = _ops.has_depth
backproject = _ops.backproject
warp_point = _ops.warp_point
photometric_row = _ops.photometric_row
robust_weight = _ops.robust_weight
add_row = _ops.add_row
pair_weight = _ops.pair_weight


# ----------------------------------------------------------------------------------------------
# Reduction


@cuda.jit(device=True)
def _zero(acc):
    for s in range(NV):
        acc[s] = 0.0


@cuda.jit(device=True)
def _block_reduce(acc, shared, partials):
    """Tree reduction of every thread's NV sums in shared memory; thread 0 writes the block's."""
    t = cuda.threadIdx.x
    for s in range(NV):
        shared[s, t] = acc[s]
    cuda.syncthreads()
    half = BLOCK // 2
    while half > 0:
        if t < half:
            for s in range(NV):
                shared[s, t] += shared[s, t + half]
        cuda.syncthreads()
        half //= 2
    if t == 0:
        for s in range(NV):
            partials[cuda.blockIdx.x, s] = shared[s, 0]


# ----------------------------------------------------------------------------------------------
# ICP


@cuda.jit
def _icp_kernel(vertices, normals, poses, mv, mn, camera, limits, robust, out):
    # `poses` = (pose, current camera to model camera) stacked, `camera` = (fx, fy, cx, cy),
    # `limits` = (squared distance, cos angle), `robust` = host.robust_terms
    pose, to_model = poses[0], poses[1]
    shared = cuda.shared.array((NV, BLOCK), float64)
    acc = cuda.local.array(NV, float64)
    _zero(acc)
    width = vertices.shape[1]
    n = vertices.shape[0] * width
    for i in range(cuda.grid(1), n, cuda.gridsize(1)):
        v = i // width
        u = i - v * width
        ok, px, py, pz, nx, ny, nz = map_point(vertices, normals, v, u)
        if ok:
            acc[NV - 1] += 1.0
            kept, wx, wy, wz, qx, qy, qz, ux, uy, uz = icp_match(
                (px, py, pz), (nx, ny, nz), pose, to_model, mv, mn, camera, limits
            )
            if kept:
                j0, j1, j2, j3, j4, j5, r = point_to_plane_row(
                    (wx, wy, wz), (qx, qy, qz), (ux, uy, uz)
                )
                w = pair_weight(r, pz, robust)
                add_row(acc, (j0, j1, j2, j3, j4, j5), r, w)
    _block_reduce(acc, shared, out)


@cuda.jit
def _associate_kernel(points, normals, poses, mv, mn, camera, limits, count, out):
    pose, to_model = poses[0], poses[1]
    k = cuda.grid(1)
    if k < points.shape[1]:
        point = (points[0, k], points[1, k], points[2, k])
        normal = (normals[0, k], normals[1, k], normals[2, k])
        kept, wx, wy, wz, qx, qy, qz, ux, uy, uz = icp_match(
            point, normal, pose, to_model, mv, mn, camera, limits
        )
        if kept:
            slot = cuda.atomic.add(count, 0, 1)
            out[0, slot], out[1, slot], out[2, slot] = wx, wy, wz
            out[3, slot], out[4, slot], out[5, slot] = qx, qy, qz
            out[6, slot], out[7, slot], out[8, slot] = ux, uy, uz


@cuda.jit
def _point_to_plane_kernel(world, mv, mn, jacobian, residuals):
    k = cuda.grid(1)
    if k < world.shape[1]:
        j0, j1, j2, j3, j4, j5, r = point_to_plane_row(
            (world[0, k], world[1, k], world[2, k]),
            (mv[0, k], mv[1, k], mv[2, k]),
            (mn[0, k], mn[1, k], mn[2, k]),
        )
        jacobian[0, k], jacobian[1, k], jacobian[2, k] = j0, j1, j2
        jacobian[3, k], jacobian[4, k], jacobian[5, k] = j3, j4, j5
        residuals[k] = r


@cuda.jit
def _accumulate_kernel(jacobian, residuals, weights, weighted, out):
    shared = cuda.shared.array((NV, BLOCK), float64)
    acc = cuda.local.array(NV, float64)
    _zero(acc)
    for k in range(cuda.grid(1), residuals.shape[0], cuda.gridsize(1)):
        w = weights[k] if weighted else 1.0
        row = (
            jacobian[0, k],
            jacobian[1, k],
            jacobian[2, k],
            jacobian[3, k],
            jacobian[4, k],
            jacobian[5, k],
        )
        add_row(acc, row, residuals[k], w)
    _block_reduce(acc, shared, out)


# ----------------------------------------------------------------------------------------------
# RGB-D


@cuda.jit
def _interest_kernel(dx, dy, depth, g2, use_depth, max_depth, count, indices):
    """Algorithm 1: a shared-memory list per block, one global atomic per block."""
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
        keep = is_interest(dx, dy, v, u, g2)
        if keep and use_depth:
            keep = has_depth(depth, v, u, max_depth)
        if keep:
            local[cuda.atomic.add(local_count, 0, 1)] = i
    cuda.syncthreads()
    if t == 0:
        base[0] = cuda.atomic.add(count, 0, local_count[0])
    cuda.syncthreads()
    if t < local_count[0]:
        indices[base[0] + t] = local[t]


@cuda.jit
def _interest_data_kernel(indices, depth, intensity, dx, dy, camera, points, values, grad):
    k = cuda.grid(1)
    if k < indices.shape[0]:
        width = depth.shape[1]
        i = indices[k]
        v = i // width
        u = i - v * width
        x, y, z = backproject(u, v, float(depth[v, u]), camera)
        points[0, k] = x
        points[1, k] = y
        points[2, k] = z
        values[k] = float(intensity[v, u])
        grad[0, k] = float(dx[v, u])
        grad[1, k] = float(dy[v, u])


@cuda.jit
def _correspond_kernel(
    points,
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
):
    """Algorithm 2: kept pairs listed per block in shared memory, then each adds r^2 to the
    global sum (tally[1]) and takes its slot in the global list (counted in tally[0], a float64
    that counts exactly to 2^53) with atomics. `poses` = (relative, pose, previous) stacked."""
    relative, pose = poses[0], poses[1]
    local = cuda.shared.array(BLOCK, int64)
    local_r = cuda.shared.array(BLOCK, float64)
    local_count = cuda.shared.array(1, int32)
    t = cuda.threadIdx.x
    if t == 0:
        local_count[0] = 0
    cuda.syncthreads()
    k = cuda.grid(1)
    if k < points.shape[1]:
        ok, r, wx, wy, wz, x, y, z, gx, gy = warp_point(
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
            local_r[slot] = r
    cuda.syncthreads()
    if t < local_count[0]:
        r = local_r[t]
        cuda.atomic.add(tally, 1, r * r)
        pairs[int(cuda.atomic.add(tally, 0, 1.0))] = local[t]


@cuda.jit
def _correspondence_data_kernel(
    pairs,
    n_pairs,
    points,
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
        ok, r, wx, wy, wz, x, y, z, gx, gy = warp_point(
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


@cuda.jit
def _rgbd_rows_kernel(
    pairs,
    tally,
    points,
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
):
    """The robustly weighted photometric rows of the listed pairs, tree-reduced per block. The
    pair count and sum of r^2 are read from `tally` where _correspond_kernel left them, so the
    host waits for neither: sigma' = sqrt(sum r^2 / count), as the host computed it."""
    shared = cuda.shared.array((NV, BLOCK), float64)
    acc = cuda.local.array(NV, float64)
    _zero(acc)
    relative, pose, previous_pose = poses[0], poses[1], poses[2]
    n_pairs = int(tally[0])
    sigma = math.sqrt(tally[1] / n_pairs) if n_pairs > 0 else 0.0
    for j in range(cuda.grid(1), n_pairs, cuda.gridsize(1)):
        ok, r, wx, wy, wz, x, y, z, gx, gy = warp_point(
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
        row = photometric_row(
            (wx, wy, wz), (x, y, z), (gx, gy), previous_pose, (camera[0], camera[1])
        )
        w = robust_weight(r, sigma)
        add_row(acc, row, r, w * w)
    _block_reduce(acc, shared, out)


@cuda.jit
def _photometric_kernel(world, warped_points, gradient, previous_pose, focal, jacobian):
    k = cuda.grid(1)
    if k < world.shape[1]:
        j0, j1, j2, j3, j4, j5 = photometric_row(
            (world[0, k], world[1, k], world[2, k]),
            (warped_points[0, k], warped_points[1, k], warped_points[2, k]),
            (gradient[0, k], gradient[1, k]),
            previous_pose,
            focal,
        )
        jacobian[0, k], jacobian[1, k], jacobian[2, k] = j0, j1, j2
        jacobian[3, k], jacobian[4, k], jacobian[5, k] = j3, j4, j5


# ----------------------------------------------------------------------------------------------
# Stale sensor streams (kintinuous_ref.odometry.repeated_streams)


@cuda.jit
def _repeats_kernel(depth_before, depth_now, intensity_before, intensity_now, flags):
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


# ----------------------------------------------------------------------------------------------
# Host helpers


def stage(array):
    """A device array (uploaded once if a NumPy array is given; None stays None)."""
    return None if array is None else to_device(array)


def _f64(array):
    """A float64 device array (host arrays converted and uploaded)."""
    return to_device(array, np.float64)


def _reduction_blocks(count: int) -> int:
    return min(grid_1d(count, BLOCK), MAX_BLOCKS)


# Device arrays reused from one Gauss-Newton iteration to the next: creating one costs numba
# more host time (an allocation through the driver, a Python object, its finalizer) than the
# kernels it feeds take on the GPU. Only for arrays a call writes and reads back itself: the
# copies and kernels of the one stream run in order, so a later call's writes wait for them.
_SCRATCH: dict[tuple, Any] = {}


def _scratch(name: str, shape: tuple[int, ...], dtype: Any = np.float64) -> Any:
    key = (name, shape, np.dtype(dtype))
    if key not in _SCRATCH:
        _SCRATCH[key] = cuda.device_array(shape, dtype=dtype)
    return _SCRATCH[key]


def _upload(name: str, array: np.ndarray) -> Any:
    """`array` copied into the scratch device array `name` of its shape and type."""
    device = _scratch(name, array.shape, array.dtype)
    device.copy_to_device(np.ascontiguousarray(array))
    return device


_EMPTY_TALLY = np.zeros(2)  # [pairs listed, sum of their r^2] before Algorithm 2


def _rounded_up(count: int) -> int:
    """The power of two at or above `count` (>= 1): few shapes, so few scratch arrays."""
    return 1 << max(count - 1, 0).bit_length()


def _counter(dtype=np.int32):
    return cuda.to_device(np.zeros(1, dtype=dtype))


# ----------------------------------------------------------------------------------------------
# ICP (kintinuous_ref.odometry.icp)


def icp_system_and_valid(
    vertices,
    normals,
    model_vertices,
    model_normals,
    pose,
    model_pose,
    camera,
    distance_threshold,
    angle_threshold_deg,
    robust_kernel="none",
    robust_threshold=0.0,
    model_noise=None,
) -> tuple[LinearSystem, int]:
    """icp_system and the number of valid current points (for the inlier fraction);
    `robust_threshold` the kernel's k or c in metres (ref icp.robust_threshold), `model_noise`
    as ref icp.pair_weights'."""
    host.check_map("current vertex map", vertices, camera)
    host.check_map("current normal map", normals, camera)
    host.check_map("model vertex map", model_vertices, camera)
    host.check_map("model normal map", model_normals, camera)
    pose, to_model, dist2, cos_min = host.icp_constants(
        pose, model_pose, distance_threshold, angle_threshold_deg
    )
    blocks = _reduction_blocks(camera.height * camera.width)
    out = _scratch("icp partials", (blocks, NV))
    _icp_kernel[blocks, BLOCK](
        stage(vertices),
        stage(normals),
        _upload("icp poses", np.stack((pose, to_model))),
        stage(model_vertices),
        stage(model_normals),
        pinhole(camera),
        (dist2, cos_min),
        host.robust_terms(robust_kernel, robust_threshold, model_noise),
        out,
    )
    return host.sum_partials(out.copy_to_host())


def icp_system(
    vertices,
    normals,
    pose: np.ndarray,
    model_vertices,
    model_normals,
    model_pose: np.ndarray,
    camera: Intrinsics,
    distance_threshold: float = 0.10,
    angle_threshold_deg: float = 20.0,
    robust_kernel: str = "none",
    robust_noise: float = IcpConfig.robust_noise,
    model_noise: float | None = None,
) -> LinearSystem:
    """The 6x6 point-to-plane normal equations of one ICP iteration at one level: one thread per
    pixel(s), block tree reductions, partials added on the host."""
    return icp_system_and_valid(
        vertices,
        normals,
        model_vertices,
        model_normals,
        pose,
        model_pose,
        camera,
        distance_threshold,
        angle_threshold_deg,
        robust_kernel,
        robust_threshold(robust_kernel, robust_noise),
        model_noise,
    )[0]


def associate(
    points,
    point_normals,
    pose: np.ndarray,
    model_vertices,
    model_normals,
    model_pose: np.ndarray,
    camera: Intrinsics,
    distance_threshold: float,
    angle_threshold_deg: float,
) -> tuple:
    """Projective data association: (world point, model vertex, model normal) as (3, M) columns
    in atomic order. Model maps as (3, h*w) columns (ref map_columns)."""
    shape = (camera.height, camera.width, 3)
    host.check_image("model vertex columns", model_vertices, (3, camera.height * camera.width))
    host.check_image("model normal columns", model_normals, (3, camera.height * camera.width))
    pose, to_model, dist2, cos_min = host.icp_constants(
        pose, model_pose, distance_threshold, angle_threshold_deg
    )
    n = points.shape[1]
    if n == 0:
        empty = np.empty((3, 0))
        return empty, empty.copy(), empty.copy()
    count = _counter()
    out = cuda.device_array((9, n), dtype=np.float64)
    model_v = to_device(np.asarray(model_vertices).T.reshape(shape))
    model_n = to_device(np.asarray(model_normals).T.reshape(shape))
    _associate_kernel[grid_1d(n, BLOCK), BLOCK](
        _f64(points),
        _f64(point_normals),
        _upload("icp poses", np.stack((pose, to_model))),
        model_v,
        model_n,
        pinhole(camera),
        (dist2, cos_min),
        count,
        out,
    )
    kept = int(count.copy_to_host()[0])
    pairs = like_input(out[:, :kept], points)
    return pairs[0:3], pairs[3:6], pairs[6:9]


def point_to_plane_rows(world, model_vertices, model_normals) -> tuple:
    """Jacobian (6, N) and residuals (N,) of the point-to-plane cost at xi = 0 (eq. 9)."""
    n = world.shape[1]
    if n == 0:
        return np.empty((6, 0)), np.empty(0)
    jacobian = cuda.device_array((6, n), dtype=np.float64)
    residuals = cuda.device_array(n, dtype=np.float64)
    _point_to_plane_kernel[grid_1d(n, BLOCK), BLOCK](
        _f64(world), _f64(model_vertices), _f64(model_normals), jacobian, residuals
    )
    return like_input(jacobian, world), like_input(residuals, world)


# ----------------------------------------------------------------------------------------------
# Normal equations (kintinuous_ref.odometry.solve)


def accumulate(jacobian, residuals, weights=None) -> LinearSystem:
    """Normal equations of the (6, N) Jacobian and (N,) residuals: per-thread sums, block tree
    reductions in shared memory, block partials added on the host in float64."""
    n = residuals.shape[0]
    blocks = _reduction_blocks(n)
    out = cuda.device_array((blocks, NV), dtype=np.float64)
    d_residuals = _f64(residuals) if n else cuda.to_device(np.zeros(1))
    d_jacobian = _f64(jacobian) if n else cuda.to_device(np.zeros((6, 1)))
    weighted = weights is not None and n > 0
    _accumulate_kernel[blocks, BLOCK](
        d_jacobian, d_residuals, _f64(weights) if weighted else d_residuals, weighted, out
    )
    system = host.sum_partials(out.copy_to_host())[0]
    if n == 0:  # the placeholder row above must not count
        return LinearSystem.empty()
    return system


# ----------------------------------------------------------------------------------------------
# RGB-D (kintinuous_ref.odometry.rgbd)


def _interest_list(dx, dy, depth, min_gradient: float, max_depth: float):
    """Algorithm 1 on the device: (indices device array, count)."""
    height, width = dx.shape
    n = height * width
    count = _counter()
    indices = cuda.device_array(max(n, 1), dtype=np.int64)
    use_depth = depth is not None
    _interest_kernel[grid_1d(n, BLOCK), BLOCK](
        dx,
        dy,
        depth if use_depth else dx,
        float(min_gradient) ** 2,
        use_depth,
        float(max_depth),
        count,
        indices,
    )
    total = int(count.copy_to_host()[0])
    return indices[:total], total


def interest_points(intensity_dx, intensity_dy, min_gradient: float):
    """Algorithm 1: flat indices of the pixels with dx^2 + dy^2 >= g^2 (atomic order)."""
    host.check_image("intensity_dy", intensity_dy, intensity_dx.shape)
    indices, _ = _interest_list(stage(intensity_dx), stage(intensity_dy), None, min_gradient, 0)
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
    shape = (camera.height, camera.width)
    for name, image in (
        ("depth", depth),
        ("intensity", intensity),
        ("dx", intensity_dx),
        ("dy", intensity_dy),
    ):
        host.check_image(f"current {name} image", image, shape)
    d_depth, d_dx, d_dy = stage(depth), stage(intensity_dx), stage(intensity_dy)
    indices, n = _interest_list(d_dx, d_dy, d_depth, min_gradient, max_depth)
    size = max(n, 1)
    points = cuda.device_array((3, size), dtype=np.float64)
    values = cuda.device_array(size, dtype=np.float64)
    gradient = cuda.device_array((2, size), dtype=np.float64)
    if n:
        images = (indices, d_depth, stage(intensity), d_dx, d_dy)
        intrinsics = pinhole(camera)
        _interest_data_kernel[grid_1d(n, BLOCK), BLOCK](
            *images, intrinsics, points, values, gradient
        )
    result = (indices, points[:, :n], values[:n], gradient[:, :n])
    if not is_device(depth):
        result = tuple(array.copy_to_host() for array in result)
    return InterestPoints(*result)


def _pair_arguments(
    points,
    pose,
    previous_pose,
    previous_depth,
    previous_intensity,
    camera,
    max_depth_change,
    previous_dx,
    previous_dy,
) -> tuple:
    """The arguments warp_point needs, on the device, in the kernels' order; the three poses
    (relative, current, previous) go up as one array, one copy per iteration."""
    shape = (camera.height, camera.width)
    host.check_image("previous depth image", previous_depth, shape)
    host.check_image("previous intensity image", previous_intensity, shape)
    prev_i = stage(previous_intensity)
    warped = previous_dx is not None and previous_dy is not None
    poses = (host.relative_pose(pose, previous_pose), pose, previous_pose)
    return (
        _f64(points.points),
        _f64(points.intensity),
        _f64(points.gradient),
        _upload("rgbd poses", np.stack(poses).astype(np.float64)),
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
    tally = _upload("rgbd tally", _EMPTY_TALLY)
    if pairs is None:
        pairs = cuda.device_array(max(n, 1), dtype=np.int64)
    if n:
        _correspond_kernel[grid_1d(n, BLOCK), BLOCK](*arguments, tally, pairs)
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
    arguments = _pair_arguments(
        points,
        pose,
        previous_pose,
        previous_depth,
        previous_intensity,
        camera,
        max_depth_change,
        previous_dx,
        previous_dy,
    )
    n = points.points.shape[1]
    pairs, tally = _pair_list(arguments, n)
    kept = int(tally.copy_to_host()[0])
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
        _f64(correspondences.world),
        _f64(correspondences.warped),
        _f64(correspondences.gradient),
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
    arguments = _pair_arguments(
        points,
        pose,
        previous_pose,
        previous_depth,
        previous_intensity,
        camera,
        max_depth_change,
        previous_dx,
        previous_dy,
    )
    n = points.points.shape[1]
    if n == 0:
        return LinearSystem.empty()
    pairs = _scratch("rgbd pairs", (_rounded_up(n),), np.int64)
    pairs, tally = _pair_list(arguments, n, pairs)
    # enough blocks for every interest point kept: no count to wait for
    blocks = _rounded_up(_reduction_blocks(n))
    out = _scratch("rgbd partials", (blocks, NV))
    _rgbd_rows_kernel[blocks, BLOCK](pairs, tally, *arguments, out)
    return host.sum_partials(out.copy_to_host())[0]


# ----------------------------------------------------------------------------------------------
# Stale sensor streams


def repeated_streams(previous, current) -> tuple[bool, bool]:
    """kintinuous_ref.odometry.repeated_streams for frames on the device: the full-resolution
    images compared by one kernel, three flags downloaded (host frames: the reference's)."""
    if previous is None or not is_device(current.levels[0].depth):
        return ref_repeated_streams(previous, current)
    before, now = previous.levels[0], current.levels[0]
    if tuple(before.depth.shape) != tuple(now.depth.shape):  # images of other sizes differ
        return False, False
    flags = cuda.to_device(np.zeros(3, dtype=np.int32))
    _repeats_kernel[grid_2d(*now.depth.shape), BLOCK_2D](
        stage(before.depth), now.depth, stage(before.intensity), now.intensity, flags
    )
    any_depth, depth_differs, intensity_differs = flags.copy_to_host()
    if not any_depth:  # a blind frame is never a repeat (the reference's rule)
        return False, False
    return not depth_differs, not intensity_differs


# ----------------------------------------------------------------------------------------------
# Per-frame problems


class IcpProblem(host.IcpProblemBase):
    """kintinuous_ref.odometry.icp.IcpProblem with the CUDA kernels underneath (maps uploaded
    once per frame and level)."""


class RgbdProblem(host.RgbdProblemBase):
    """kintinuous_ref.odometry.rgbd.RgbdProblem with the CUDA kernels underneath (interest points
    stay on the device for all iterations)."""


IcpProblem.kernels = RgbdProblem.kernels = sys.modules[__name__]


class DenseTracker(host.FastDenseTracker):
    """kintinuous_ref.odometry.DenseTracker with the CUDA kernels underneath."""

    def __init__(self, method: str, config: Config, camera: Intrinsics) -> None:
        super().__init__(method, config, camera, sys.modules[__name__])


def make_tracker(method: str, config: Config, camera: Intrinsics) -> Tracker:
    """kintinuous_ref.odometry.make_tracker (every method) with the CUDA kernels underneath."""
    return host.make_tracker_with(sys.modules[__name__], method, config, camera)
