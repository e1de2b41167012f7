# ruff: noqa: ANN001, ANN201  (numba kernels: argument types come from the call)
"""kintinuous_ref.odometry.icp as CUDA kernels around icp/ops.py: one thread per pixel (a
grid-stride loop) associates, weighs and adds its rows into a local vector, and the block
reduces the vectors by a tree in shared memory (odometry/sums/cuda.py), one partial per block
for the host to add.

Same public names, signatures and results as the reference module (the names it does not
compute itself are the reference's own objects), except that lists come out in atomic order:
compare associated pairs as sets. Arrays stay where they are given (kintinuous_fast.targets.cuda):
device arrays in, device arrays out; NumPy in, NumPy out. Runs on numba's CUDA simulator too.
"""

from __future__ import annotations

import numpy as np
from numba import cuda, float64

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
    scratch,
    stage,
    upload,
    zero,
)
from kintinuous_fast.targets import pinhole, to_host
from kintinuous_fast.targets.cuda import grid_1d, kernel, like_input, to_device
from kintinuous_ref.camera import Intrinsics
from kintinuous_ref.config import IcpConfig
from kintinuous_ref.odometry.icp import depth_noise_scale as depth_noise_scale
from kintinuous_ref.odometry.icp import map_columns as map_columns
from kintinuous_ref.odometry.icp import pair_weights as pair_weights
from kintinuous_ref.odometry.icp import point_to_plane_cost as point_to_plane_cost
from kintinuous_ref.odometry.icp import robust_threshold
from kintinuous_ref.odometry.icp import robust_weights as robust_weights
from kintinuous_ref.odometry.icp import valid_points as valid_points
from kintinuous_ref.odometry.icp import voxel_noise as voxel_noise
from kintinuous_ref.odometry.solve import LinearSystem

from . import (
    NO_WEIGHTS,
    REFERENCE_NAMES,
    TARGET_NAMES,
    _IcpProblem,
    check_maps,
    icp_constants,
    robust_terms,
)
from .ops import build_ops

# The reference's own objects (REFERENCE_NAMES) and what this target computes (TARGET_NAMES),
# listed in icp/__init__.py.
__all__ = [*REFERENCE_NAMES, *TARGET_NAMES]

_ops = build_ops(DEVICE, GEOMETRY)
# Module-level names: numba resolves the device functions as globals of the kernels below.
_icp_match = _ops.icp_match
_map_point = _ops.map_point
_point_to_plane_row = _ops.point_to_plane_row
_store_point_to_plane = _ops.store_point_to_plane
_pair_weight = _ops.pair_weight


# ----------------------------------------------------------------------------------------------
# Kernels


@kernel
def icp_kernel(vertices, normals, poses, mv, mn, camera, limits, robust, out, gate, level):
    # `poses` = (pose, current camera to model camera) stacked, `camera` = (fx, fy, cx, cy),
    # `limits` = (squared distance, cos angle), `robust` = robust_terms; `gate` and `level`:
    # sums.cuda.gated (the whole block returns together, before any barrier)
    if gated(gate, level):
        return
    pose, to_model = poses[0], poses[1]
    shared = cuda.shared.array((NV, BLOCK), float64)
    acc = cuda.local.array(NV, float64)
    zero(acc)
    width = vertices.shape[1]
    n = vertices.shape[0] * width
    for i in range(cuda.grid(1), n, cuda.gridsize(1)):
        v = i // width
        u = i - v * width
        ok, px, py, pz, nx, ny, nz = _map_point(vertices, normals, v, u)
        if ok:
            acc[NV - 1] += 1.0
            kept, wx, wy, wz, qx, qy, qz, ux, uy, uz = _icp_match(
                (px, py, pz), (nx, ny, nz), pose, to_model, mv, mn, camera, limits
            )
            if kept:
                j0, j1, j2, j3, j4, j5, r = _point_to_plane_row(
                    (wx, wy, wz), (qx, qy, qz), (ux, uy, uz)
                )
                w = _pair_weight(r, pz, robust)
                add_row(acc, (j0, j1, j2, j3, j4, j5), r, w)
    block_reduce(acc, shared, out)


@kernel
def _associate_kernel(points, normals, poses, mv, mn, camera, limits, count, out):
    pose, to_model = poses[0], poses[1]
    k = cuda.grid(1)
    if k < points.shape[1]:
        point = (points[0, k], points[1, k], points[2, k])
        normal = (normals[0, k], normals[1, k], normals[2, k])
        kept, wx, wy, wz, qx, qy, qz, ux, uy, uz = _icp_match(
            point, normal, pose, to_model, mv, mn, camera, limits
        )
        if kept:
            slot = cuda.atomic.add(count, 0, 1)
            out[0, slot], out[1, slot], out[2, slot] = wx, wy, wz
            out[3, slot], out[4, slot], out[5, slot] = qx, qy, qz
            out[6, slot], out[7, slot], out[8, slot] = ux, uy, uz


@kernel
def _point_to_plane_kernel(world, mv, mn, jacobian, residuals):
    k = cuda.grid(1)
    if k < world.shape[1]:
        _store_point_to_plane(world, mv, mn, k, jacobian, residuals)


# ----------------------------------------------------------------------------------------------
# Host side


def _icp_sums(current, model, camera, constants, robust) -> tuple[LinearSystem, int]:
    """icp_system of the staged current and model (vertex, normal) maps and the number of valid
    current points (for the inlier fraction); `constants` = icp_constants, `robust` =
    robust_terms."""
    pose, to_model, dist2, cos_min = constants
    blocks = reduction_blocks(camera.height * camera.width)
    out = scratch("icp partials", (blocks, NV))
    icp_kernel[blocks, BLOCK](
        *current,
        upload("icp poses", np.stack((pose, to_model))),
        *model,
        pinhole(camera),
        (dist2, cos_min),
        robust,
        out,
        open_gate(),
        ANY_LEVEL,
    )
    return sum_partials(to_host(out))


def _icp_system_and_valid(
    vertices,
    normals,
    model_vertices,
    model_normals,
    pose,
    model_pose,
    camera,
    distance_threshold,
    angle_threshold_deg,
    robust=NO_WEIGHTS,
) -> tuple[LinearSystem, int]:
    """icp_system (its pairs weighted by `robust` = robust_terms) and the number of valid
    current points, from the maps as given (NumPy or device arrays)."""
    check_maps("current", vertices, normals, camera)
    check_maps("model", model_vertices, model_normals, camera)
    constants = icp_constants(pose, model_pose, distance_threshold, angle_threshold_deg)
    current, model = (
        (stage(vertices), stage(normals)),
        (stage(model_vertices), stage(model_normals)),
    )
    return _icp_sums(current, model, camera, constants, robust)


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
    robust = robust_terms(robust_kernel, robust_threshold(robust_kernel, robust_noise), model_noise)
    maps = (vertices, normals, model_vertices, model_normals)
    limits = (distance_threshold, angle_threshold_deg)
    return _icp_system_and_valid(*maps, pose, model_pose, camera, *limits, robust)[0]


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
    check_image("model vertex columns", model_vertices, (3, camera.height * camera.width))
    check_image("model normal columns", model_normals, (3, camera.height * camera.width))
    pose, to_model, dist2, cos_min = icp_constants(
        pose, model_pose, distance_threshold, angle_threshold_deg
    )
    n = points.shape[1]
    if n == 0:
        empty = np.empty((3, 0))
        return empty, empty.copy(), empty.copy()
    count = counter()
    out = cuda.device_array((9, n), dtype=np.float64)
    model_v = to_device(np.asarray(model_vertices).T.reshape(shape))
    model_n = to_device(np.asarray(model_normals).T.reshape(shape))
    _associate_kernel[grid_1d(n, BLOCK), BLOCK](
        f64(points),
        f64(point_normals),
        upload("icp poses", np.stack((pose, to_model))),
        model_v,
        model_n,
        pinhole(camera),
        (dist2, cos_min),
        count,
        out,
    )
    kept = int(to_host(count)[0])
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
        f64(world), f64(model_vertices), f64(model_normals), jacobian, residuals
    )
    return like_input(jacobian, world), like_input(residuals, world)


class IcpProblem(_IcpProblem):
    """kintinuous_ref.odometry.icp.IcpProblem with the CUDA kernels underneath (maps uploaded
    once per frame and level)."""

    stage = staticmethod(stage)

    def points(self, level: int) -> tuple:
        """The level's current vertex and normal maps, checked and uploaded once (the kernel
        tests each pixel for a valid point itself)."""
        if level not in self._points:
            current = self.current_levels[level]
            check_maps("current", current.vertices, current.normals, current.camera)
            self._points[level] = (stage(current.vertices), stage(current.normals))
        return self._points[level]

    def system_and_valid(self, level: int, pose: np.ndarray) -> tuple[LinearSystem, int]:
        camera = self.current_levels[level].camera
        return _icp_sums(
            self.points(level), self.model(level), camera, self.constants(pose), self.robust
        )
