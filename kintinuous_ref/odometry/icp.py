"""KinectFusion's ICP: frame-to-model point-to-plane alignment (paper V-B, eq. 6-10).

The current frame's vertex map v (camera frame) is aligned to the model predicted by raycasting
the TSDF from the previous pose: vertex and normal maps (v_m, n_m) in the world frame. Data
association is projective (no search): a current vertex, moved into the world by the current
estimate T, is projected into the camera the model was rendered from and paired with whatever model
vertex lies on that pixel. Pairs farther apart than 0.10 m, or whose normals differ by more than
20 degrees, are rejected. The point-to-plane cost (eq. 6)

    E_icp = sum_k ((exp(xi) T v_k - v_m^k) . n_m^k)^2

linearised at xi = 0 with p = T v (eq. 7-9), exp(xi) p ~ p + omega x p + u, gives per pair

    r_k = (p - v_m) . n_m,   J_k = [ (p x n_m)^T, n_m^T ]    (as omega . (p x n) = (omega x p) . n)

and the 6x6 normal equations of solve.py. Coarse-to-fine over three pyramid levels,
10 / 5 / 4 iterations from finest to coarsest (run coarsest first).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from kintinuous_ref import se3
from kintinuous_ref.camera import Intrinsics
from kintinuous_ref.odometry.solve import LinearSystem, accumulate


def associate(
    vertices: np.ndarray,
    normals: np.ndarray,
    pose: np.ndarray,
    model_vertices: np.ndarray,
    model_normals: np.ndarray,
    model_pose: np.ndarray,
    camera: Intrinsics,
    distance_threshold: float,
    angle_threshold_deg: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Projective data association (KinectFusion): (world point, model vertex, model normal).

    vertices, normals: (h, w, 3) current frame, camera frame, NaN = invalid.
    pose: current estimate of the camera-to-world pose.
    model_vertices, model_normals: (h, w, 3) raycast maps in the world frame, rendered from
    model_pose with the intrinsics `camera` (the same level as the current maps).
    Returns three (N, 3) float64 arrays of the pairs that pass the distance and angle tests.
    """
    rotation, translation = pose[:3, :3], pose[:3, 3]
    points = vertices.reshape(-1, 3).astype(np.float64)
    point_normals = normals.reshape(-1, 3).astype(np.float64)
    valid = np.isfinite(points).all(axis=1) & np.isfinite(point_normals).all(axis=1)
    world = points[valid] @ rotation.T + translation
    world_normals = point_normals[valid] @ rotation.T

    # Project into the model's camera and take the nearest pixel (no interpolation, as KinFu).
    in_model_camera = se3.transform_points(se3.inverse(model_pose), world)
    z = in_model_camera[:, 2]
    in_front = z > 1e-6
    safe_z = np.where(in_front, z, 1.0)
    u = np.rint(camera.fx * in_model_camera[:, 0] / safe_z + camera.cx)
    v = np.rint(camera.fy * in_model_camera[:, 1] / safe_z + camera.cy)
    height, width = model_vertices.shape[:2]
    inside = in_front & (u >= 0) & (u < width) & (v >= 0) & (v < height)
    world, world_normals = world[inside], world_normals[inside]
    pixel = v[inside].astype(np.int64) * width + u[inside].astype(np.int64)
    matched = model_vertices.reshape(-1, 3)[pixel].astype(np.float64)
    matched_normals = model_normals.reshape(-1, 3)[pixel].astype(np.float64)

    # Reject pairs without a model surface, too far apart, or facing different ways.
    distance = np.linalg.norm(world - matched, axis=1)
    cos_angle = np.sum(world_normals * matched_normals, axis=1)
    with np.errstate(invalid="ignore"):
        keep = (distance <= distance_threshold) & (
            cos_angle >= np.cos(np.radians(angle_threshold_deg))
        )
    return world[keep], matched[keep], matched_normals[keep]


def point_to_plane_rows(
    world: np.ndarray, model_vertices: np.ndarray, model_normals: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Jacobian rows (N, 6) and residuals (N,) of the point-to-plane cost at xi = 0 (eq. 9)."""
    residuals = np.sum((world - model_vertices) * model_normals, axis=1)
    jacobian = np.concatenate([np.cross(world, model_normals), model_normals], axis=1)
    return jacobian, residuals


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
) -> LinearSystem:
    """The 6x6 point-to-plane normal equations of one ICP iteration at one pyramid level."""
    world, matched, matched_normals = associate(
        vertices,
        normals,
        pose,
        model_vertices,
        model_normals,
        model_pose,
        camera,
        distance_threshold,
        angle_threshold_deg,
    )
    jacobian, residuals = point_to_plane_rows(world, matched, matched_normals)
    return accumulate(jacobian, residuals)


def point_to_plane_cost(
    xi: np.ndarray,
    world: np.ndarray,
    model_vertices: np.ndarray,
    model_normals: np.ndarray,
) -> np.ndarray:
    """Residuals ((exp(xi) p - v_m) . n_m) for fixed pairs (eq. 6): the truth for Jacobian tests."""
    moved = se3.transform_points(se3.exp(xi), world)
    return np.sum((moved - model_vertices) * model_normals, axis=1)


class IcpProblem:
    """ICP for one frame: the current pyramid against the model pyramid, any pose estimate."""

    def __init__(
        self,
        current_levels: Sequence,
        model_levels: Sequence[tuple[np.ndarray, np.ndarray]],
        model_pose: np.ndarray,
        distance_threshold: float = 0.10,
        angle_threshold_deg: float = 20.0,
    ) -> None:
        # current_levels: PyramidLevel-like (camera, vertices, normals); model_levels: world-frame
        # (vertices, normals) of the raycast, downsampled like the current frame (model_pyramid).
        self.current_levels = current_levels
        self.model_levels = model_levels
        self.model_pose = model_pose
        self.distance_threshold = distance_threshold
        self.angle_threshold_deg = angle_threshold_deg

    def system(self, level: int, pose: np.ndarray) -> LinearSystem:
        current = self.current_levels[level]
        model_vertices, model_normals = self.model_levels[level]
        return icp_system(
            current.vertices,
            current.normals,
            pose,
            model_vertices,
            model_normals,
            self.model_pose,
            current.camera,
            self.distance_threshold,
            self.angle_threshold_deg,
        )

    def inlier_fraction(self, pose: np.ndarray) -> float:
        """Matched pairs per valid current vertex at full resolution (0 when none is valid)."""
        current = self.current_levels[0]
        valid = int(
            np.sum(
                np.isfinite(current.vertices).all(axis=2) & np.isfinite(current.normals).all(axis=2)
            )
        )
        return self.system(0, pose).count / valid if valid else 0.0
