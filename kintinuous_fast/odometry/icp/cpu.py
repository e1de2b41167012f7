# ruff: noqa: ANN001, ANN201  (numba loops: argument types come from the call)
"""kintinuous_ref.odometry.icp on the CPU: loops on all threads around icp/ops.py.

Same public names, signatures and results as the reference module (tests/test_fast_odometry.py
states the tolerances; the names it does not compute itself are the reference's own objects).
The valid current points are compacted once per frame and level (`_valid_points`); each
iteration then associates, weighs and sums them block by block in one pass, nothing stored per
pair, into fixed-chunk partial sums (odometry/sums/cpu.py). Lists come out in the reference's
order.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from kintinuous_fast.odometry import check_image
from kintinuous_fast.odometry.rgbd.cpu import RgbdProblem
from kintinuous_fast.odometry.sums import chunks_for, sum_partials
from kintinuous_fast.odometry.sums.cpu import (
    ALLOCATING_LOOP,
    BLOCK,
    CHUNKS,
    LOOP,
    partials,
    row_starts,
    run,
    stage,
)
from kintinuous_fast.targets import pinhole
from kintinuous_fast.targets.cache import register_slowest
from kintinuous_fast.targets.cpu import claimed_items
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

from . import REFERENCE_NAMES, TARGET_NAMES, _IcpProblem, check_maps, icp_constants, robust_terms
from .cpu_block import OPS as _OPS
from .cpu_block import _block_work, icp_chunk, kept_pairs
from .cpu_joint import FUSED_WEIGHTINGS, joint_level, joint_system

# The reference's own objects (REFERENCE_NAMES) and what this target computes (TARGET_NAMES),
# listed in icp/__init__.py.
__all__ = [*REFERENCE_NAMES, *TARGET_NAMES]

# Module-level names: numba resolves the scalar functions as globals of the loops below.
_icp_match = _OPS.icp_match
_map_point = _OPS.map_point
_store_point_to_plane = _OPS.store_point_to_plane
_weighs_pairs = _OPS.weighs_pairs


# ----------------------------------------------------------------------------------------------
# Loops


@LOOP
def _valid_counts(claims, parts, vertices, normals, counts):
    """counts[v] = the valid current points (finite vertex and normal) of row v."""
    for v in claimed_items(claims, vertices.shape[0], parts):
        count = 0
        for u in range(vertices.shape[1]):
            count += _map_point(vertices, normals, v, u)[0]
        counts[v] = count


@LOOP
def _compact_loop(claims, parts, vertices, normals, starts, points):
    """The valid current points as columns (px, py, pz, nx, ny, nz) in row-major order, row v's
    from column starts[v]."""
    for v in claimed_items(claims, vertices.shape[0], parts):
        k = starts[v]
        for u in range(vertices.shape[1]):
            ok, px, py, pz, nx, ny, nz = _map_point(vertices, normals, v, u)
            if ok:
                points[0, k], points[1, k], points[2, k] = px, py, pz
                points[3, k], points[4, k], points[5, k] = nx, ny, nz
                k += 1


@register_slowest("odometry")
@ALLOCATING_LOOP
def _icp_loop(claims, parts, points, pose, to_model, mv, mn, camera, limits, robust, out):
    """Association + point-to-plane row + accumulation over the valid current points (6, n);
    out[c] collects chunk c's rows (icp_chunk). `robust` = robust_terms: the weights of the
    rows."""
    for c in claimed_items(claims, out.shape[0], parts):
        icp_chunk(c, points, pose, to_model, mv, mn, camera, limits, robust, out)


@ALLOCATING_LOOP
def _icp_pairs_loop(claims, parts, points, pose, to_model, mv, mn, camera, limits, out):
    """out[c] = (valid current points, ICP pairs) of chunk c: the counts of _icp_loop without
    its sums."""
    n = points.shape[1]
    chunks = out.shape[0]
    for c in claimed_items(claims, chunks, parts):
        work = _block_work(mv.dtype)
        start, stop = c * n // chunks, (c + 1) * n // chunks
        pairs = 0
        for block in range(start, stop, BLOCK):
            end = min(block + BLOCK, stop)
            pairs += kept_pairs(points, block, end, pose, to_model, mv, mn, camera, limits, work)
        out[c, 0] = stop - start
        out[c, 1] = pairs


@LOOP
def _associate_loop(
    claims, parts, points, normals, pose, to_model, mv, mn, camera, limits, keep, out
):
    for k in claimed_items(claims, points.shape[1], parts):
        point = (points[0, k], points[1, k], points[2, k])
        normal = (normals[0, k], normals[1, k], normals[2, k])
        kept, wx, wy, wz, qx, qy, qz, ux, uy, uz = _icp_match(
            point, normal, pose, to_model, mv, mn, camera, limits
        )
        keep[k] = kept
        out[0, k], out[1, k], out[2, k] = wx, wy, wz
        out[3, k], out[4, k], out[5, k] = qx, qy, qz
        out[6, k], out[7, k], out[8, k] = ux, uy, uz


@LOOP
def _point_to_plane_loop(claims, parts, world, mv, mn, jacobian, residuals):
    for k in claimed_items(claims, world.shape[1], parts):
        _store_point_to_plane(world, mv, mn, k, jacobian, residuals)


# ----------------------------------------------------------------------------------------------
# Host side


def _valid_points(vertices, normals) -> np.ndarray:
    """The valid current points (finite vertex and normal) as (6, n) columns (px, py, pz, nx, ny,
    nz) in the reference's row-major order (ref `valid_points`), in the maps' own precision: the
    loops turn each value into float64 as they read it, as the reference does once for all, and
    float32 columns halve what every ICP iteration reads (level 0: ~13 -> ~6.5 MB). Depends on
    the frame only: the ICP problem computes it once per level, not per iteration."""
    counts = np.empty(vertices.shape[0], dtype=np.int64)
    run(_valid_counts, vertices.shape[0] * vertices.shape[1], vertices, normals, counts)
    starts, n = row_starts(counts)
    points = np.empty((6, n), dtype=np.result_type(vertices, normals))
    run(_compact_loop, vertices.shape[0] * vertices.shape[1], vertices, normals, starts, points)
    return points


def _current_points(vertices, normals, camera) -> np.ndarray:
    """_valid_points of the current maps, checked against the camera."""
    check_maps("current", vertices, normals, camera)
    return _valid_points(vertices, normals)


def _loop_arguments(model, camera, constants) -> tuple:
    """What every ICP loop takes after the points: (pose, current camera to model camera, model
    vertex and normal maps, (fx, fy, cx, cy), (squared distance, cos angle)); `constants` =
    icp_constants."""
    pose, to_model, dist2, cos_min = constants
    return (pose, to_model, *model, pinhole(camera), (dist2, cos_min))


def _points_system(points, model, camera, constants, robust) -> tuple[LinearSystem, int]:
    """icp_system of the valid current points (`_valid_points`) against the staged `model` maps,
    and their number (for the inlier fraction); `robust` = robust_terms."""
    out = partials(points.shape[1])
    run(_icp_loop, points.shape[1], points, *_loop_arguments(model, camera, constants), robust, out)
    return sum_partials(out)


def _points_pairs(points, model, camera, constants) -> tuple[int, int]:
    """(ICP pairs, valid current points) of _points_system, counted without its sums."""
    out = np.zeros((chunks_for(points.shape[1], CHUNKS), 2))
    run(_icp_pairs_loop, points.shape[1], points, *_loop_arguments(model, camera, constants), out)
    valid, pairs = out.sum(axis=0)
    return int(pairs), int(valid)


def icp_system(
    vertices: np.ndarray,
    normals: np.ndarray,
    pose: np.ndarray,
    model_vertices: np.ndarray,
    model_normals: np.ndarray,
    model_pose: np.ndarray,
    camera: Intrinsics,
    distance_threshold: float = 0.10,
    angle_threshold_deg: float = 20.0,
    robust_kernel: str = "none",
    robust_noise: float = IcpConfig.robust_noise,
    model_noise: float | None = None,
) -> LinearSystem:
    """The 6x6 point-to-plane normal equations of one ICP iteration at one level: association,
    rows and sums in one pass over the current maps (nothing is stored per pair)."""
    robust = robust_terms(robust_kernel, robust_threshold(robust_kernel, robust_noise), model_noise)
    points = _current_points(stage(vertices), stage(normals), camera)
    model = (stage(model_vertices), stage(model_normals))
    check_maps("model", *model, camera)
    constants = icp_constants(pose, model_pose, distance_threshold, angle_threshold_deg)
    return _points_system(points, model, camera, constants, robust)[0]


def associate(
    points: np.ndarray,
    point_normals: np.ndarray,
    pose: np.ndarray,
    model_vertices: np.ndarray,
    model_normals: np.ndarray,
    model_pose: np.ndarray,
    camera: Intrinsics,
    distance_threshold: float,
    angle_threshold_deg: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Projective data association: (world point, model vertex, model normal) as (3, M) columns,
    in the reference's order. Model maps as (3, h*w) columns (ref map_columns)."""
    shape = (camera.height, camera.width, 3)
    check_image("model vertex columns", model_vertices, (3, camera.height * camera.width))
    check_image("model normal columns", model_normals, (3, camera.height * camera.width))
    pose, to_model, dist2, cos_min = icp_constants(
        pose, model_pose, distance_threshold, angle_threshold_deg
    )
    points = np.ascontiguousarray(points, dtype=np.float64)
    point_normals = np.ascontiguousarray(point_normals, dtype=np.float64)
    keep = np.empty(points.shape[1], dtype=np.bool_)
    out = np.empty((9, points.shape[1]))
    run(
        _associate_loop,
        points.shape[1],
        points,
        point_normals,
        pose,
        to_model,
        np.ascontiguousarray(np.asarray(model_vertices).T.reshape(shape)),
        np.ascontiguousarray(np.asarray(model_normals).T.reshape(shape)),
        pinhole(camera),
        (dist2, cos_min),
        keep,
        out,
    )
    kept = np.compress(keep, out, axis=1)
    return kept[0:3], kept[3:6], kept[6:9]


def point_to_plane_rows(
    world: np.ndarray, model_vertices: np.ndarray, model_normals: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Jacobian (6, N) and residuals (N,) of the point-to-plane cost at xi = 0 (eq. 9)."""
    n = world.shape[1]
    jacobian = np.empty((6, n))
    residuals = np.empty(n)
    run(
        _point_to_plane_loop,
        n,
        np.ascontiguousarray(world, dtype=np.float64),
        np.ascontiguousarray(model_vertices, dtype=np.float64),
        np.ascontiguousarray(model_normals, dtype=np.float64),
        jacobian,
        residuals,
    )
    return jacobian, residuals


def _fuses(rgbd: Any, weighting: str) -> bool:
    """Whether the joint loop (icp/cpu_joint.py) sums the joint system with `rgbd`: the CPU's
    RgbdProblem and a degeneracy-aware weighting."""
    return weighting in FUSED_WEIGHTINGS and isinstance(rgbd, RgbdProblem)


class IcpProblem(_IcpProblem):
    """kintinuous_ref.odometry.icp.IcpProblem with the CPU loops underneath; each level's valid
    current points are compacted once, on first use, for all of its iterations."""

    stage = staticmethod(stage)

    def points(self, level: int) -> np.ndarray:
        """The level's valid current points as (6, n) columns (_valid_points), computed once."""
        if level not in self._points:
            current = self.current_levels[level]
            vertices, normals = stage(current.vertices), stage(current.normals)
            self._points[level] = _current_points(vertices, normals, current.camera)
        return self._points[level]

    def system_and_valid(self, level: int, pose: np.ndarray) -> tuple[LinearSystem, int]:
        camera = self.current_levels[level].camera
        return _points_system(
            self.points(level), self.model(level), camera, self.constants(pose), self.robust
        )

    def joint_system_with(
        self,
        rgbd: Any,
        level: int,
        pose: np.ndarray,
        rgbd_weight: float,
        weighting: str,
        degeneracy_threshold: float,
    ) -> LinearSystem | None:
        """combined.joint_system of this problem's and `rgbd`'s systems at `pose` (the camera
        position pose[:3, 3]) in one parallel call (icp/cpu_joint.py), where `rgbd` is the
        CPU's RgbdProblem and the weighting a degeneracy-aware one; None elsewhere."""
        if not _fuses(rgbd, weighting):
            return None
        return joint_system(self, rgbd, level, pose, rgbd_weight, degeneracy_threshold)

    def refine_joint_level(
        self,
        rgbd: Any,
        level: int,
        pose: np.ndarray,
        steps: tuple[int, int, float],
        joint: tuple[float, str, float],
    ) -> tuple[np.ndarray, str] | None:
        """solve.refine over one level of the joint system of joint_system_with, every step
        compiled (JointLevel.refine): (pose, reason); `steps` = (steps, min_count, converged),
        `joint` = (rgbd_weight, weighting, degeneracy_threshold). None where joint_system_with
        is, or where the level's loop runs on the helper team."""
        rgbd_weight, weighting, threshold = joint
        if not _fuses(rgbd, weighting):
            return None
        return joint_level(self, rgbd, level).refine(pose, *steps, (rgbd_weight, threshold))

    def refine_level(
        self, level: int, pose: np.ndarray, steps: int, min_count: int, converged: float
    ) -> tuple[np.ndarray, str] | None:
        """solve.refine's steps at one level over this problem's system alone, all in compiled
        code (JointLevel.refine, the joint loop without RGB-D points): (pose, '') or (pose so
        far, why a step failed); None where the loop runs on the helper team, or where a subclass
        computes a `system` of its own."""
        if type(self).system is not IcpProblem.system:
            return None
        level_terms = joint_level(self, None, level)
        return level_terms.refine(pose, steps, min_count, converged, (0.0, 0.0))

    def inlier_fraction(self, pose: np.ndarray, level: int = 0) -> float:
        """As the base class, from the pair count alone (_points_pairs): no sums for this one
        look."""
        camera = self.current_levels[level].camera
        pairs, valid = _points_pairs(
            self.points(level), self.model(level), camera, self.constants(pose)
        )
        return pairs / valid if valid else 0.0
