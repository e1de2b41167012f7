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

Robust residual weights (`config.icp.robust_kernel`). Least squares lets every pair pull in
proportion to its residual, so the pairs that fit worst - stray normals of the voxelised model at
depth edges, a surface seen for the first time, a moving object - pull hardest. An M-estimator
replaces r^2 by rho(r) and is minimised by iteratively reweighted least squares: each Gauss-Newton
step weights pair k by w(r_k) = rho'(r_k) / r_k at the current estimate,

    A = sum_k w_k J_k^T J_k,   b = sum_k w_k J_k^T r_k.

    "huber":  w(r) = 1 for |r| <= k, k / |r| beyond      (quadratic core, linear tails)
    "tukey":  w(r) = (1 - (r / c)^2)^2 for |r| < c, 0 beyond   (biweight: outliers drop out)

k = 1.345 sigma and c = 4.685 sigma are the classical tunings with 95 % of least squares'
efficiency on Gaussian residuals of spread sigma. sigma is `config.icp.robust_noise`, a fixed
length in metres (5 mm: the depth noise of a structured-light sensor at 1-2 m plus the
voxelisation of a ~1 cm model), not a per-iteration estimate such as the median absolute
deviation: a median needs every residual stored and sorted each iteration, where a fixed scale
keeps the CPU and CUDA kernels one pass over the pixels, and the coarse-to-fine start, whose
residuals are still dominated by the motion, would inflate a data-driven scale exactly when the
outliers should be cut.

Depth noise weights (`model_noise`, from config.icp.depth_noise). A structured-light camera's
depth error grows with the square of the depth (camera.axial_noise: 1.9 mm at 1 m, 14 mm at 3 m),
and the model's surface carries the voxelisation's error on top, about voxel / sqrt(12) (a
uniform error over one voxel). So a pair whose current point lies at depth z has the spread

    sigma(z)^2 = axial_noise(z)^2 + model_noise^2,

and the pairs are weighted by their information: each residual is scaled by
s = sigma(1 m) / sigma(z) before the robust kernel reads it, and the pair's weight is
w(s r) s^2. A pair at 1 m weighs as without the model, so `robust_noise` keeps its meaning
there; a far pair, whose noise the kernel would otherwise read as misfit, counts for less. On the
synthetic corridor at 640x480 this takes the combined tracker's ATE from 4.6 to 2.9 mm, and on
redkitchen `icp` from 23.7 to 21.4 mm (docs/odometry.md has the whole suite). None: every pair
the same.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from kintinuous_ref import se3
from kintinuous_ref.camera import Intrinsics, axial_noise
from kintinuous_ref.config import IcpConfig
from kintinuous_ref.errors import ConfigError
from kintinuous_ref.odometry.solve import LinearSystem, accumulate
from kintinuous_ref.vocabulary import ROBUST_KERNELS

# The kernels' thresholds in units of the residual spread sigma: 95 % asymptotic efficiency of
# least squares when the residuals are Gaussian (Huber 1964; Beaton and Tukey 1974).
HUBER_TUNING = 1.345
TUKEY_TUNING = 4.685
# Depth noise weights (module docstring): a pair at this depth (metres) keeps its weight.
REFERENCE_DEPTH = 1.0


def robust_threshold(kernel: str, noise: float) -> float:
    """The kernel's threshold in metres: Huber's k or Tukey's c for residual spread `noise`."""
    if kernel not in ROBUST_KERNELS:
        raise ConfigError(f"icp.robust_kernel must be one of {ROBUST_KERNELS}, got {kernel!r}")
    if not noise > 0:
        raise ConfigError(f"icp.robust_noise must be > 0 metres, got {noise}")
    return {"none": 0.0, "huber": HUBER_TUNING, "tukey": TUKEY_TUNING}[kernel] * noise


def robust_weights(residuals: np.ndarray, kernel: str, threshold: float) -> np.ndarray | None:
    """IRLS weights w(r) = rho'(r) / r of the point-to-plane residuals (module docstring), None
    for "none" (least squares). `threshold`: Huber's k or Tukey's c in metres."""
    if kernel == "none":
        return None
    magnitude = np.abs(residuals)
    if kernel == "huber":
        return np.where(magnitude <= threshold, 1.0, threshold / np.maximum(magnitude, 1e-300))
    if kernel == "tukey":
        ratio = residuals / threshold
        inside = 1.0 - ratio * ratio
        return np.where(magnitude < threshold, inside * inside, 0.0)
    raise ConfigError(f"icp.robust_kernel must be one of {ROBUST_KERNELS}, got {kernel!r}")


def voxel_noise(voxel_size: float) -> float:
    """The model's noise for the depth noise weights: a uniform error over one voxel,
    voxel / sqrt(12) (module docstring)."""
    return voxel_size / float(np.sqrt(12.0))


def depth_noise_scale(depths: np.ndarray, model_noise: float) -> np.ndarray:
    """s = sigma(REFERENCE_DEPTH) / sigma(z) of pairs at camera depths z, with sigma(z)^2 =
    axial_noise(z)^2 + model_noise^2 (module docstring)."""
    reference = axial_noise(REFERENCE_DEPTH) ** 2 + model_noise**2
    return np.sqrt(reference / (axial_noise(depths) ** 2 + model_noise**2))


def pair_weights(
    residuals: np.ndarray,
    depths: np.ndarray,
    kernel: str,
    threshold: float,
    model_noise: float | None = None,
) -> np.ndarray | None:
    """Each pair's weight in the normal equations: the robust weight of its residual in units of
    the noise at its depth, times its information s^2 (module docstring); without `model_noise`
    robust_weights alone. None: least squares, every weight 1."""
    if model_noise is None:
        return robust_weights(residuals, kernel, threshold)
    scale = depth_noise_scale(depths, model_noise)
    robust = robust_weights(scale * residuals, kernel, threshold)
    return scale**2 if robust is None else robust * scale**2


def map_columns(vertices: np.ndarray, normals: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A (h, w, 3) vertex and normal map as float64 columns (3, h*w), NaN kept (model maps)."""
    return (
        np.ascontiguousarray(vertices.reshape(-1, 3).T, dtype=np.float64),
        np.ascontiguousarray(normals.reshape(-1, 3).T, dtype=np.float64),
    )


def valid_points(vertices: np.ndarray, normals: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The valid vertices and normals of a (h, w, 3) map as float64 columns (3, N).

    Columns (x, y and z each contiguous) make the per-point arithmetic below several times faster
    than (N, 3) rows.
    """
    points = vertices.reshape(-1, 3)
    point_normals = normals.reshape(-1, 3)
    valid = np.isfinite(points).all(axis=1) & np.isfinite(point_normals).all(axis=1)
    return (
        np.ascontiguousarray(points[valid].T, dtype=np.float64),
        np.ascontiguousarray(point_normals[valid].T, dtype=np.float64),
    )


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
    """Projective data association (KinectFusion): (world point, model vertex, model normal).

    points, point_normals: (3, N) valid current vertices and normals, camera frame
    (`valid_points`). pose: current estimate of the camera-to-world pose.
    model_vertices, model_normals: the raycast maps in the world frame as (3, h*w) columns
    (`map_columns`), rendered from model_pose with the intrinsics `camera` (the same level as
    the current points).
    Returns three (3, M) float64 column arrays of the pairs that pass the distance and angle tests.
    """
    world = pose[:3, :3] @ points + pose[:3, 3:4]
    # Project into the model's camera and take the nearest pixel (no interpolation, as KinFu).
    to_model = se3.inverse(model_pose) @ pose
    x, y, z = to_model[:3, :3] @ points + to_model[:3, 3:4]
    in_front = z > 1e-6
    safe_z = np.where(in_front, z, 1.0)
    u = np.rint(camera.fx * x / safe_z + camera.cx)
    v = np.rint(camera.fy * y / safe_z + camera.cy)
    height, width = camera.height, camera.width
    inside = np.flatnonzero(in_front & (u >= 0) & (u < width) & (v >= 0) & (v < height))
    pixel = v[inside].astype(np.int64) * width + u[inside].astype(np.int64)
    # np.take along an axis is much faster than fancy indexing a[:, index].
    world = np.take(world, inside, axis=1)
    matched = np.take(model_vertices, pixel, axis=1)
    matched_normals = np.take(model_normals, pixel, axis=1)
    world_normals = pose[:3, :3] @ np.take(point_normals, inside, axis=1)

    # Reject pairs without a model surface (NaN fails both tests), too far apart, or facing
    # different ways.
    difference = world - matched
    squared_distance = np.einsum("in,in->n", difference, difference)
    cos_angle = np.einsum("in,in->n", world_normals, matched_normals)
    with np.errstate(invalid="ignore"):
        keep = (squared_distance <= distance_threshold**2) & (
            cos_angle >= np.cos(np.radians(angle_threshold_deg))
        )
    return (
        np.compress(keep, world, axis=1),
        np.compress(keep, matched, axis=1),
        np.compress(keep, matched_normals, axis=1),
    )


def point_to_plane_rows(
    world: np.ndarray, model_vertices: np.ndarray, model_normals: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Jacobian (6, N) and residuals (N,) of the point-to-plane cost at xi = 0 (eq. 9).

    Inputs are (3, N) columns: p = T v in the world, the matched model vertex and normal.
    """
    residuals = np.einsum("in,in->n", world - model_vertices, model_normals)
    jacobian = np.concatenate([np.cross(world, model_normals, axis=0), model_normals], axis=0)
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
    robust_kernel: str = "none",
    robust_noise: float = IcpConfig.robust_noise,
    model_noise: float | None = None,
) -> LinearSystem:
    """The 6x6 point-to-plane normal equations of one ICP iteration at one pyramid level.

    vertices, normals: (h, w, 3) current maps (camera frame, NaN = invalid); model_vertices,
    model_normals: (h, w, 3) raycast maps (world frame, NaN = no surface); robust_kernel,
    robust_noise: the IRLS weights; model_noise: the depth noise weights (module docstring);
    the rest as in `associate`.
    """
    points, point_normals = valid_points(vertices, normals)
    return _system(
        robust_kernel,
        robust_threshold(robust_kernel, robust_noise),
        model_noise,
        points,
        point_normals,
        pose,
        *map_columns(model_vertices, model_normals),
        model_pose,
        camera,
        distance_threshold,
        angle_threshold_deg,
    )


def _system(
    kernel: str,
    threshold: float,
    model_noise: float | None,
    points: np.ndarray,
    point_normals: np.ndarray,
    pose: np.ndarray,
    *model_arguments: object,
) -> LinearSystem:
    world, matched, matched_normals = associate(points, point_normals, pose, *model_arguments)
    jacobian, residuals = point_to_plane_rows(world, matched, matched_normals)
    # The depths of the paired current points, back in the camera frame.
    depths = pose[:3, 2] @ (world - pose[:3, 3:4])
    weights = pair_weights(residuals, depths, kernel, threshold, model_noise)
    return accumulate(jacobian, residuals, weights)


def point_to_plane_cost(
    xi: np.ndarray,
    world: np.ndarray,
    model_vertices: np.ndarray,
    model_normals: np.ndarray,
) -> np.ndarray:
    """Residuals ((exp(xi) p - v_m) . n_m) for fixed (3, N) pairs (eq. 6): the truth for tests."""
    step = se3.exp(xi)
    moved = step[:3, :3] @ world + step[:3, 3:4]
    return np.einsum("in,in->n", moved - model_vertices, model_normals)


class IcpProblem:
    """ICP for one frame: the current pyramid against the model pyramid, any pose estimate."""

    def __init__(
        self,
        current_levels: Sequence,
        model_levels: Sequence[tuple[np.ndarray, np.ndarray]],
        model_pose: np.ndarray,
        distance_threshold: float = 0.10,
        angle_threshold_deg: float = 20.0,
        robust_kernel: str = "none",
        robust_noise: float = IcpConfig.robust_noise,
        model_noise: float | None = None,
    ) -> None:
        # current_levels: PyramidLevel-like (camera, vertices, normals); model_levels: world-frame
        # (vertices, normals) of the raycast, downsampled like the current frame (model_pyramid).
        self.current_levels = current_levels
        self.model_levels = model_levels
        self.model_pose = model_pose
        self.distance_threshold = distance_threshold
        self.angle_threshold_deg = angle_threshold_deg
        self.robust_kernel = robust_kernel
        self.robust_threshold = robust_threshold(robust_kernel, robust_noise)
        self.model_noise = model_noise
        self._points: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        self._model: dict[int, tuple[np.ndarray, np.ndarray]] = {}

    def points(self, level: int) -> tuple[np.ndarray, np.ndarray]:
        """The valid current vertices and normals of a level, (3, N) columns, computed once."""
        if level not in self._points:
            current = self.current_levels[level]
            self._points[level] = valid_points(current.vertices, current.normals)
        return self._points[level]

    def model(self, level: int) -> tuple[np.ndarray, np.ndarray]:
        """The model maps of a level as (3, h*w) columns, computed once."""
        if level not in self._model:
            self._model[level] = map_columns(*self.model_levels[level])
        return self._model[level]

    def system(self, level: int, pose: np.ndarray) -> LinearSystem:
        return _system(
            self.robust_kernel,
            self.robust_threshold,
            self.model_noise,
            *self.points(level),
            pose,
            *self.model(level),
            self.model_pose,
            self.current_levels[level].camera,
            self.distance_threshold,
            self.angle_threshold_deg,
        )

    def inlier_fraction(self, pose: np.ndarray, level: int = 0) -> float:
        """Matched pairs per valid current vertex at a pyramid level (0 when none is valid)."""
        valid = self.points(level)[0].shape[1]
        return self.system(level, pose).count / valid if valid else 0.0
