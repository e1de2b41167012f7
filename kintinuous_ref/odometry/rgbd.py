"""Dense RGB-D odometry of Steinbruecker et al. as the paper implements it (section IV).

Frame-to-frame photoconsistency between the previous raw frame n and the current frame n+1. The
unknown is the camera-to-world pose T of the current frame; the motion between the frames is
T_rel = T_prev^-1 T (current camera -> previous camera).

1. Interest points (Algorithm 1): the pixels of the current intensity image whose gradient is at
   least the level's minimum, dI/dx^2 + dI/dy^2 >= g^2, kept as a LIST of pixel indices (the
   paper's optimisation over OpenCV's mask). They and their 3D points X = M_{n+1}(p) K^-1 (p, 1)
   are computed once per level, before iterating.
2. Correspondences (Algorithm 2, eq. 2): each point is warped into the previous image,
   z' (x', y', 1) = K R K^-1 (z p) + K t, i.e. X' = T_rel X projected by K. The pair is kept when
   the warped pixel lies inside the image and the previous depth there agrees with z' to within
   d_s = 0.07 m (occlusions and depth edges fail this test).
3. Residual r = I_n(p') - I_{n+1}(p) (intensity units 0..255; I_n sampled bilinearly so that the
   cost varies smoothly with sub-pixel motion). Its derivative with respect to the left twist xi of
   T (T' = exp(xi) T, eq. 4-5) by the chain rule is

       J = grad I . dpi/dX' . R_prev^T [ -[p]_x  I ],   p = T X the point in the world,

   with dpi/dX' = [[fx/z', 0, -fx x'/z'^2], [0, fy/z', -fy y'/z'^2]]. As in Steinbruecker's and
   OpenCV's implementation (and the paper, which computes derivatives for the current frame only)
   grad I is the current image's gradient at p by default (`gradient="current"`): at convergence
   I_n(p') = I_{n+1}(p), so both images have the same gradient there, and the fixed gradient makes
   each step cheaper. `gradient="warped"` uses the previous image's gradient sampled at p', the
   exact derivative of the cost (used by the finite-difference tests).
4. Weighting (IV-A.3): sigma' = sqrt(sigma / k_c), the root mean square of the residuals of the
   k_c correspondences; each row (J_k, r_k) is scaled by w_k = 1 / (sigma' + |r_k|), as in
   Steinbruecker's formulation and the authors' code, so the normal equations weight a pair by
   w_k^2. Large differences (occlusions, specularities) thus have bounded influence, and the
   weighted residual w_k r_k is dimensionless, which is what eq. 11's w = 0.1 is weighed against.
5. Least squares (eq. 3) for the increment, T' = exp(xi) T, four levels coarse-to-fine,
   10 / 7 / 7 / 7 iterations from finest to coarsest.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from kintinuous_ref.camera import Intrinsics
from kintinuous_ref.errors import ConfigError
from kintinuous_ref.odometry.solve import LinearSystem, accumulate
from kintinuous_ref.vocabulary import GRADIENTS


@dataclass
class InterestPoints:
    """Algorithm 1's output for one level of the current frame, with what iterating needs."""

    indices: np.ndarray  # (N,) int64 flat pixel indices into the level's image
    points: np.ndarray  # (3, N) float64 camera-frame 3D points of the current frame (columns)
    intensity: np.ndarray  # (N,) float64 current intensity I_{n+1}(p)
    gradient: np.ndarray  # (2, N) float64 current (dI/dx, dI/dy) at p, units per pixel


def interest_points(
    intensity_dx: np.ndarray, intensity_dy: np.ndarray, min_gradient: float
) -> np.ndarray:
    """Algorithm 1: flat indices of the pixels with dx^2 + dy^2 >= g^2 (a list, not a mask)."""
    squared = intensity_dx.astype(np.float64) ** 2 + intensity_dy.astype(np.float64) ** 2
    return np.flatnonzero(squared >= float(min_gradient) ** 2)


def prepare_level(
    depth: np.ndarray,
    intensity: np.ndarray,
    intensity_dx: np.ndarray,
    intensity_dy: np.ndarray,
    camera: Intrinsics,
    min_gradient: float,
    max_depth: float,
) -> InterestPoints:
    """Interest points of the current frame at one level and their 3D points (IV-A.2)."""
    indices = interest_points(intensity_dx, intensity_dy, min_gradient)
    z = depth.reshape(-1)[indices].astype(np.float64)
    has_depth = (z > 0) & (z <= max_depth) & np.isfinite(z)
    indices, z = indices[has_depth], z[has_depth]
    width = depth.shape[1]
    u, v = indices % width, indices // width
    points = np.stack([(u - camera.cx) * z / camera.fx, (v - camera.cy) * z / camera.fy, z])
    gradient = np.stack(
        [intensity_dx.reshape(-1)[indices], intensity_dy.reshape(-1)[indices]]
    ).astype(np.float64)
    return InterestPoints(
        indices, points, intensity.reshape(-1)[indices].astype(np.float64), gradient
    )


def sample_bilinear(image: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Bilinear interpolation of `image` at (u, v), which must lie in [0, w-1] x [0, h-1]."""
    height, width = image.shape[:2]
    u0 = np.clip(np.floor(u).astype(np.int64), 0, width - 2)
    v0 = np.clip(np.floor(v).astype(np.int64), 0, height - 2)
    a, b = u - u0, v - v0
    flat = image.reshape(height * width, *image.shape[2:]).astype(np.float64)
    top = flat[v0 * width + u0] * (1 - a) + flat[v0 * width + u0 + 1] * a
    bottom = flat[(v0 + 1) * width + u0] * (1 - a) + flat[(v0 + 1) * width + u0 + 1] * a
    return top * (1 - b) + bottom * b


# Pixels: how far past the image's border pixel centres a warped point may land (rounding).
BORDER_SLACK = 1e-6


@dataclass
class Correspondences:
    """Algorithm 2's output: the kept pairs (p, p', I_{n+1}(p) - I_n(p')) and what J needs."""

    world: np.ndarray  # (3, N) p = T X, current points in the world under the current estimate
    warped: np.ndarray  # (3, N) X' = T_rel X, in the previous camera's frame
    residuals: np.ndarray  # (N,) I_n(p') - I_{n+1}(p)
    gradient: np.ndarray  # (2, N) the image gradient used in J
    kept: np.ndarray  # (N,) indices into the InterestPoints arrays


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
    """Algorithm 2: warp the interest points into the previous frame (eq. 2) and keep the valid.

    With previous_dx/dy given, the gradient is the previous image's at p' ("warped" mode),
    otherwise the current image's at p.
    """
    relative = np.linalg.inv(previous_pose) @ pose
    warped = relative[:3, :3] @ points.points + relative[:3, 3:4]
    x, y, z = warped
    safe_z = np.where(z > 1e-6, z, 1.0)
    u = camera.fx * x / safe_z + camera.cx
    v = camera.fy * y / safe_z + camera.cy
    height, width = previous_depth.shape
    # Inside the image with room for the bilinear 2x2 neighbourhood. A border pixel warped by
    # (nearly) the identity lands on its own centre only to within rounding, on either side
    # depending on the order of the floating-point operations: BORDER_SLACK keeps it inside
    # whichever way it rounds (sample_bilinear clips, so the slack reads the border values).
    lo, hi_u, hi_v = -BORDER_SLACK, width - 1 + BORDER_SLACK, height - 1 + BORDER_SLACK
    inside = (z > 1e-6) & (u >= lo) & (u <= hi_u) & (v >= lo) & (v <= hi_v)
    kept = np.flatnonzero(inside)
    u, v, z = u[kept], v[kept], z[kept]
    # The depth test (d_s) at the nearest pixel, as Algorithm 2 reads M_n(p').
    nearest = np.rint(v).astype(np.int64) * width + np.rint(u).astype(np.int64)
    d = previous_depth.reshape(-1)[nearest].astype(np.float64)
    agree = (d > 0) & (np.abs(z - d) < max_depth_change)
    kept, u, v = kept[agree], u[agree], v[agree]
    residuals = sample_bilinear(previous_intensity, u, v) - points.intensity[kept]
    if previous_dx is not None and previous_dy is not None:
        gradient = np.stack(
            [sample_bilinear(previous_dx, u, v), sample_bilinear(previous_dy, u, v)]
        )
    else:
        gradient = np.take(points.gradient, kept, axis=1)
    world = pose[:3, :3] @ np.take(points.points, kept, axis=1) + pose[:3, 3:4]
    return Correspondences(world, np.take(warped, kept, axis=1), residuals, gradient, kept)


def photometric_rows(
    correspondences: Correspondences, previous_pose: np.ndarray, camera: Intrinsics
) -> tuple[np.ndarray, np.ndarray]:
    """Unweighted Jacobian (6, N) and residuals (N,) of the intensity differences at xi = 0."""
    x, y, z = correspondences.warped
    gx, gy = correspondences.gradient
    # a = grad I . dpi/dX' (one column per pair, previous camera frame) ...
    a = np.stack(
        [gx * camera.fx / z, gy * camera.fy / z, -(gx * camera.fx * x + gy * camera.fy * y) / z**2]
    )
    # ... turned into the world frame, c = R_prev a; then c . (omega x p + u) = omega.(p x c) + u.c
    c = previous_pose[:3, :3] @ a
    jacobian = np.concatenate([np.cross(correspondences.world, c, axis=0), c], axis=0)
    return jacobian, correspondences.residuals


def robust_row_weights(residuals: np.ndarray) -> np.ndarray:
    """w_k = 1 / (sigma' + |r_k|) with sigma' = sqrt(sum r^2 / k_c) (paper IV-A.3)."""
    if len(residuals) == 0:
        return np.zeros(0)
    sigma = float(np.sqrt(np.mean(residuals**2)))
    denominator = sigma + np.abs(residuals)
    # All residuals exactly zero (a perfect match) leaves nothing to normalise: weight 1.
    return np.where(denominator > 1e-12, 1.0 / np.maximum(denominator, 1e-12), 1.0)


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
    """The 6x6 normal equations of one RGB-D iteration at one level (eq. 3), robustly weighted."""
    pairs = correspond(
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
    jacobian, residuals = photometric_rows(pairs, previous_pose, camera)
    row_weights = robust_row_weights(residuals)
    return accumulate(jacobian, residuals, row_weights**2)


def photometric_residuals(
    xi: np.ndarray,
    points: InterestPoints,
    kept: np.ndarray,
    pose: np.ndarray,
    previous_pose: np.ndarray,
    previous_intensity: np.ndarray,
    camera: Intrinsics,
) -> np.ndarray:
    """r(xi) = I_n(pi(T_prev^-1 exp(xi) T X)) - I_{n+1}(p) for fixed pairs: the truth for tests."""
    from kintinuous_ref import se3

    moved = se3.exp(xi) @ pose
    relative = np.linalg.inv(previous_pose) @ moved
    x, y, z = relative[:3, :3] @ points.points[:, kept] + relative[:3, 3:4]
    u = camera.fx * x / z + camera.cx
    v = camera.fy * y / z + camera.cy
    return sample_bilinear(previous_intensity, u, v) - points.intensity[kept]


def check_gradient(gradient: str) -> None:
    """A one-line ConfigError unless `gradient` is one of GRADIENTS (RgbdProblem's argument)."""
    if gradient not in GRADIENTS:
        raise ConfigError(f"rgbd.gradient must be 'current' or 'warped', got {gradient!r}")


class RgbdProblem:
    """RGB-D odometry for one frame pair: interest points once per level, then any pose."""

    # What the problem computes with: Algorithm 1 per level, the system of a pose, and `stage`,
    # which puts an image where those two read it (once per frame and level). This is the seam
    # of a fast backend, whose RgbdProblem is this class over its own loops or kernels; here
    # the NumPy arrays are read where they are.
    prepare_level = staticmethod(prepare_level)
    rgbd_system = staticmethod(rgbd_system)

    @staticmethod
    def stage(image: np.ndarray | None) -> np.ndarray | None:
        return image

    def __init__(
        self,
        previous_levels: Sequence,
        current_levels: Sequence,
        previous_pose: np.ndarray,
        min_gradient: Sequence[float] = (12.0, 5.0, 3.0, 1.0),
        max_depth_change: float = 0.07,
        max_depth: float = 6.0,
        gradient: str = "current",
    ) -> None:
        # *_levels: PyramidLevel-like (camera, depth, intensity, intensity_dx, intensity_dy).
        check_gradient(gradient)
        self.previous_levels = previous_levels
        self.current_levels = current_levels
        self.previous_pose = previous_pose
        self.min_gradient = tuple(min_gradient)
        self.max_depth_change = max_depth_change
        self.max_depth = max_depth
        self.gradient = gradient
        self._points: dict[int, InterestPoints] = {}
        self._previous: dict[int, tuple] = {}

    def points(self, level: int) -> InterestPoints:
        """Algorithm 1 for a level of the current frame, computed on first use."""
        if level not in self._points:
            current = self.current_levels[level]
            stage = self.stage
            threshold = self.min_gradient[min(level, len(self.min_gradient) - 1)]
            self._points[level] = self.prepare_level(
                stage(current.depth),
                stage(current.intensity),
                stage(current.intensity_dx),
                stage(current.intensity_dy),
                current.camera,
                threshold,
                self.max_depth,
            )
        return self._points[level]

    def previous(self, level: int) -> tuple:
        """The previous frame's images of a level that rgbd_system reads: depth, intensity and,
        in "warped" mode, the gradients (else None)."""
        if level not in self._previous:
            previous = self.previous_levels[level]
            stage = self.stage
            warped = self.gradient == "warped"
            self._previous[level] = (
                stage(previous.depth),
                stage(previous.intensity),
                stage(previous.intensity_dx) if warped else None,
                stage(previous.intensity_dy) if warped else None,
            )
        return self._previous[level]

    def system(self, level: int, pose: np.ndarray) -> LinearSystem:
        depth, intensity, dx, dy = self.previous(level)
        return self.rgbd_system(
            self.points(level),
            pose,
            self.previous_pose,
            depth,
            intensity,
            self.previous_levels[level].camera,
            self.max_depth_change,
            dx,
            dy,
        )

    def inlier_fraction(self, pose: np.ndarray, level: int = 0) -> float:
        """Correspondences per interest point at a pyramid level (0 when there is none)."""
        total = len(self.points(level).indices)
        return self.system(level, pose).count / total if total else 0.0
