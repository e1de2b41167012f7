"""FOVIS: sparse feature-based visual odometry (Huang et al. 2011), which the paper switches to.

"Visual Odometry and Mapping for Autonomous Flight Using an RGB-D Camera" (ISRR 2011) estimates the
motion between two RGB-D frames from FAST corners. It runs on the CPU, as in the paper (V-A).
Per frame pair the steps are:

1. Features: FAST corners on each level of the Gaussian intensity pyramid, spread over the image by
   bucketing (at most a few of the strongest per grid cell), kept only where the depth is valid and
   smooth over the patch. The descriptor is the 9x9 patch of intensities around the corner minus
   its mean (illumination offsets cancel).
2. Initial rotation: the coarsest images are aligned by a 3-DOF rotation (Gauss-Newton on the
   photometric error under a pure-rotation homography K R K^-1) so that each feature's search
   window is centred where it is expected to move.
3. Matching: for each feature, the descriptor nearest in L2 among the features of the other frame on
   the same level inside the search window; a match is kept only if it is the best in both
   directions (mutual consistency). The current feature's position is then refined to sub-pixel
   accuracy by aligning its patch to the previous one (Lucas-Kanade on the 2D shift).
4. Inliers: two matches are consistent when the rigid motion preserves the distance between their
   3D points. The largest set of mutually consistent matches (a clique of the consistency graph) is
   grown greedily from the best-connected match (Howard 2008).
5. Motion: absolute orientation (Horn / Umeyama, closed form) on the 3D inlier pairs, refined by
   minimising the reprojection error in both images; matches reprojecting worse than a threshold
   are rejected and the motion is estimated once more.

The increment returned follows the project's convention: the current camera expressed in the
previous camera's frame, so that p_previous = increment @ p_current and
current_pose = previous_pose @ increment.

Simplifications against the original: a fixed FAST threshold (FOVIS adapts it to hold a feature
count), the initial rotation and the sub-pixel alignment by plain Gauss-Newton instead of ESM, no
keyframes (always the previous frame) and the reprojection refinement by scipy's least squares on
the 6-DOF twist. One addition: corners whose patch straddles a depth discontinuity are dropped.
Such a corner (an object's silhouette against the background) is not a fixed point of the scene:
under motion the background slides behind it, its patch alignment is pulled towards the
background's smaller parallax, and its depth belongs to either side. On noise-free synthetic
sequences these corners biased every increment the same way (about 3 % too short).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import cv2
import numpy as np
from scipy.optimize import least_squares
from scipy.spatial.distance import cdist

from kintinuous_ref import se3
from kintinuous_ref.camera import Intrinsics
from kintinuous_ref.config import FovisConfig
from kintinuous_ref.errors import TrackingError

if TYPE_CHECKING:
    from kintinuous_ref.preprocess import PreprocessedFrame, PyramidLevel

# Sub-pixel refinement: Gauss-Newton steps, and how far (pixels) a patch may slide from its corner.
_SUBPIXEL_ITERATIONS = 6
_SUBPIXEL_REACH = 2
# Bilinear depth at a sub-pixel position only where the 4 neighbours agree to this fraction; across
# a depth edge the interpolated depth belongs to neither surface.
_DEPTH_AGREEMENT = 0.03
# An initial rotation estimate larger than this (radians) is implausible at 30 Hz: ignore it.
_MAX_INITIAL_ROTATION = 0.35


@dataclass
class FovisResult:
    increment: np.ndarray  # 4x4 relative motion (previous <- current); identity when not ok
    ok: bool
    reason: str = ""
    inliers: int = 0


@dataclass
class Features:
    """FAST corners of one frame, over all pyramid levels."""

    levels: np.ndarray  # (N,) int, pyramid level each corner was found on
    pixels: np.ndarray  # (N, 2) float64 (u, v) in pixels OF ITS LEVEL
    points: np.ndarray  # (N, 3) float64 camera-frame 3D points (metres)
    descriptors: np.ndarray  # (N, (2r+1)^2) float32 patch intensities minus their mean
    responses: np.ndarray  # (N,) float32 FAST corner score

    def __len__(self) -> int:
        return len(self.levels)

    def subset(self, keep: np.ndarray) -> Features:
        return Features(
            self.levels[keep],
            self.pixels[keep],
            self.points[keep],
            self.descriptors[keep],
            self.responses[keep],
        )


# --------------------------------------------------------------------------------------------
# 1. Features
# --------------------------------------------------------------------------------------------


def detect_features(frame: PreprocessedFrame, camera: Intrinsics, config: FovisConfig) -> Features:
    """FAST corners with valid depth and patch descriptors on the first feature_levels levels."""
    full_depth = frame.levels[0].depth
    parts = []
    for level in range(min(config.feature_levels, len(frame.levels))):
        parts.append(
            _detect_on_level(
                frame.levels[level].intensity,
                full_depth,
                smooth_depth_mask(
                    frame.levels[level].depth, config.patch_radius, config.patch_depth_variation
                ),
                camera,
                level,
                config,
            )
        )
    return Features(*(np.concatenate(arrays) for arrays in zip(*parts, strict=True)))


def _detect_on_level(
    intensity: np.ndarray,
    full_depth: np.ndarray,
    smooth_depth: np.ndarray,
    camera: Intrinsics,
    level: int,
    config: FovisConfig,
) -> tuple[np.ndarray, ...]:
    height, width = intensity.shape
    pixels, responses = fast_corners(intensity, config.fast_threshold)
    # Corners whose patch (plus the sub-pixel search around it) leaves the image have no descriptor.
    margin = config.patch_radius + _SUBPIXEL_REACH + 1
    u, v = pixels[:, 0], pixels[:, 1]
    inside = (u >= margin) & (u < width - margin) & (v >= margin) & (v < height - margin)
    pixels, responses = pixels[inside], responses[inside]
    # As in FOVIS, a corner of any level takes its depth from the full-resolution depth image at
    # its level-0 position (2^l u, 2^l v): a smoothed coarse depth would blend across creases.
    z = full_depth[pixels[:, 1] << level, pixels[:, 0] << level].astype(np.float64)
    has_depth = (z > 0) & smooth_depth[pixels[:, 1], pixels[:, 0]]
    pixels, responses, z = pixels[has_depth], responses[has_depth], z[has_depth]

    # Coarser levels cover the same image with 4x fewer pixels: a 4x smaller feature budget.
    budget = config.max_features // 4**level
    cell = max(1, round(config.bucket_size / 2**level))
    keep = bucket_strongest(pixels, responses, cell, budget, (height, width))
    pixels, responses, z = pixels[keep], responses[keep], z[keep]

    points = _backproject_points(pixels * 2.0**level, z, camera)
    descriptors = patch_descriptors(intensity, pixels, config.patch_radius)
    return (
        np.full(len(pixels), level, dtype=np.int64),
        pixels.astype(np.float64),
        points,
        descriptors,
        responses,
    )


def smooth_depth_mask(depth: np.ndarray, radius: int, variation: float) -> np.ndarray:
    """True where the depth inside the (2r+1)^2 patch is complete and free of discontinuities.

    Min and max filters of the level's depth: a hole (0) or a spread of more than `variation`
    (a fraction of the depth) marks a silhouette; a tilted plane stays well inside 10 % (Kinect
    noise of about 1 % at 2 m too).
    """
    kernel = np.ones((2 * radius + 1, 2 * radius + 1), np.uint8)
    depth = depth.astype(np.float32)
    nearest, farthest = cv2.erode(depth, kernel), cv2.dilate(depth, kernel)
    return (nearest > 0) & (farthest - nearest <= variation * farthest)


def fast_corners(intensity: np.ndarray, threshold: int) -> tuple[np.ndarray, np.ndarray]:
    """FAST-9 corners (OpenCV, non-maximum suppressed): (N, 2) int pixels (u, v) and scores."""
    image = np.clip(np.rint(intensity), 0, 255).astype(np.uint8)
    detector = cv2.FastFeatureDetector_create(threshold=int(threshold), nonmaxSuppression=True)
    keypoints = detector.detect(image)
    if not keypoints:
        return np.zeros((0, 2), dtype=np.int64), np.zeros(0, dtype=np.float32)
    pixels = np.rint(cv2.KeyPoint_convert(keypoints)).astype(np.int64)
    responses = np.array([keypoint.response for keypoint in keypoints], dtype=np.float32)
    return pixels, responses


def bucket_strongest(
    pixels: np.ndarray, responses: np.ndarray, cell: int, budget: int, shape: tuple[int, int]
) -> np.ndarray:
    """Indices of at most `budget` corners, spread evenly over a grid of cell x cell buckets.

    Each bucket keeps its strongest ceil(budget / buckets) corners, so that a richly textured
    corner of the image cannot take the whole budget (a spread of features constrains the motion
    better); the strongest `budget` of those survive.
    """
    if budget <= 0 or len(pixels) == 0:
        return np.zeros(0, dtype=np.int64)
    columns = -(-shape[1] // cell)
    buckets = (pixels[:, 1] // cell) * columns + pixels[:, 0] // cell
    per_bucket = -(-budget // (columns * -(-shape[0] // cell)))
    # Sort by bucket, strongest first inside a bucket; a corner's rank is its position minus the
    # position of its bucket's first corner.
    order = np.lexsort((-responses, buckets))
    sorted_buckets = buckets[order]
    first_of_bucket = np.searchsorted(sorted_buckets, sorted_buckets, side="left")
    rank = np.arange(len(order)) - first_of_bucket
    kept = order[rank < per_bucket]
    strongest = kept[np.argsort(-responses[kept], kind="stable")[:budget]]
    return np.sort(strongest)


def patch_descriptors(intensity: np.ndarray, pixels: np.ndarray, radius: int) -> np.ndarray:
    """(N, (2r+1)^2) patches around integer pixels minus their mean (Huang et al.: 9x9)."""
    offsets = np.arange(-radius, radius + 1)
    dv, du = np.meshgrid(offsets, offsets, indexing="ij")
    patches = intensity[
        pixels[:, 1, None] + dv.ravel()[None, :], pixels[:, 0, None] + du.ravel()[None, :]
    ].astype(np.float32)
    return patches - patches.mean(axis=1, keepdims=True)


def _backproject_points(pixels: np.ndarray, z: np.ndarray, camera: Intrinsics) -> np.ndarray:
    x = (pixels[:, 0] - camera.cx) * z / camera.fx
    y = (pixels[:, 1] - camera.cy) * z / camera.fy
    return np.stack([x, y, z], axis=1)


# --------------------------------------------------------------------------------------------
# 2. Initial rotation
# --------------------------------------------------------------------------------------------


def estimate_initial_rotation(
    previous_intensity: np.ndarray,
    current_intensity: np.ndarray,
    camera: Intrinsics,
    iterations: int = 10,
) -> np.ndarray:
    """Rotation R (previous <- current) that best aligns two small images, by Gauss-Newton.

    Under a pure rotation a previous pixel x maps to the current pixel pi(K W K^-1 x) with W = R^T
    (a homography, whatever the depth). W is updated as exp(delta) W, minimising
    sum (I_cur(pi(K W K^-1 x)) - I_prev(x))^2. Translation is ignored: at the coarsest pyramid
    level a few centimetres move the image by less than a pixel, while a few degrees move it by
    several.
    """
    previous = cv2.GaussianBlur(previous_intensity.astype(np.float32), (5, 5), 1.0)
    current = cv2.GaussianBlur(current_intensity.astype(np.float32), (5, 5), 1.0)
    grad_x = cv2.Sobel(current, cv2.CV_32F, 1, 0, ksize=3) / 8.0
    grad_y = cv2.Sobel(current, cv2.CV_32F, 0, 1, ksize=3) / 8.0
    height, width = previous.shape
    rays = camera.ray_directions().reshape(-1, 3).astype(np.float64)
    reference = previous.ravel().astype(np.float64)
    rotation_cur_prev = np.eye(3)
    for _ in range(iterations):
        q = rays @ rotation_cur_prev.T
        u = camera.fx * q[:, 0] / q[:, 2] + camera.cx
        v = camera.fy * q[:, 1] / q[:, 2] + camera.cy
        # Keep one pixel from the border so the bilinear samples and gradients are genuine.
        valid = (q[:, 2] > 0) & (u >= 1) & (u <= width - 2) & (v >= 1) & (v <= height - 2)
        if valid.sum() < 20:
            return np.eye(3)
        map_u = u.reshape(height, width).astype(np.float32)
        map_v = v.reshape(height, width).astype(np.float32)
        samples = [
            cv2.remap(image, map_u, map_v, cv2.INTER_LINEAR).ravel()[valid].astype(np.float64)
            for image in (current, grad_x, grad_y)
        ]
        warped, gx, gy = samples
        qv = q[valid]
        # a = dI/dq = grad I . d pi / d q; the update d q = delta x q gives J = q x a.
        z = qv[:, 2]
        a = np.stack(
            [
                gx * camera.fx / z,
                gy * camera.fy / z,
                -(gx * camera.fx * qv[:, 0] + gy * camera.fy * qv[:, 1]) / z**2,
            ],
            axis=1,
        )
        jacobian = np.cross(qv, a)
        residual = warped - reference[valid]
        try:
            delta = np.linalg.solve(jacobian.T @ jacobian, -jacobian.T @ residual)
        except np.linalg.LinAlgError:
            return np.eye(3)
        rotation_cur_prev = se3.exp(np.concatenate([delta, np.zeros(3)]))[:3, :3] @ (
            rotation_cur_prev
        )
        if np.linalg.norm(delta) < 1e-6:
            break
    if se3.rotation_angle(rotation_cur_prev) > _MAX_INITIAL_ROTATION:
        return np.eye(3)
    return rotation_cur_prev.T


def predict_pixels(features: Features, rotation: np.ndarray, camera: Intrinsics) -> np.ndarray:
    """Where previous features appear in the current image under a pure rotation (level pixels)."""
    scale = 2.0 ** features.levels[:, None]
    base = features.pixels * scale  # level-0 pixel coordinates (pyrDown convention of camera.py)
    rays = np.stack(
        [
            (base[:, 0] - camera.cx) / camera.fx,
            (base[:, 1] - camera.cy) / camera.fy,
            np.ones(len(base)),
        ],
        axis=1,
    )
    q = rays @ rotation  # rotation.T applied to each ray: previous frame -> current frame
    z = np.maximum(q[:, 2], 1e-6)
    predicted = np.stack([camera.fx * q[:, 0] / z + camera.cx, camera.fy * q[:, 1] / z + camera.cy])
    return predicted.T / scale


# --------------------------------------------------------------------------------------------
# 3. Matching
# --------------------------------------------------------------------------------------------


def match_features(
    previous: Features, current: Features, predicted: np.ndarray, search_radius: float
) -> tuple[np.ndarray, np.ndarray]:
    """Mutually-best descriptor matches (previous index, current index) on the same level.

    `predicted` holds each previous feature's expected position in the current image; candidates
    lie within search_radius (per axis, pixels of the level) of it. L2 distances come from one
    matrix product per level, ||a-b||^2 = ||a||^2 + ||b||^2 - 2 a.b.
    """
    matched_previous, matched_current = [], []
    for level in np.intersect1d(previous.levels, current.levels):
        rows = np.flatnonzero(previous.levels == level)
        columns = np.flatnonzero(current.levels == level)
        a, b = previous.descriptors[rows], current.descriptors[columns]
        distance = (a * a).sum(1)[:, None] + (b * b).sum(1)[None, :] - 2.0 * (a @ b.T)
        outside = (
            np.abs(predicted[rows, 0, None] - current.pixels[None, columns, 0]) > search_radius
        ) | (np.abs(predicted[rows, 1, None] - current.pixels[None, columns, 1]) > search_radius)
        distance[outside] = np.inf
        best_column = np.argmin(distance, axis=1)
        best_row = np.argmin(distance, axis=0)
        row_index = np.arange(len(rows))
        mutual = (best_row[best_column] == row_index) & np.isfinite(
            distance[row_index, best_column]
        )
        matched_previous.append(rows[mutual])
        matched_current.append(columns[best_column[mutual]])
    if not matched_previous:
        return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)
    return np.concatenate(matched_previous), np.concatenate(matched_current)


def refine_subpixel(
    previous: Features,
    current: Features,
    current_levels: list[PyramidLevel],
    camera: Intrinsics,
    patch_radius: int,
) -> tuple[Features, np.ndarray]:
    """Move matched current features to the sub-pixel position that best fits the previous patch.

    FAST corners sit on integer pixels in each image independently, so a match is off by up to
    half a pixel. Like FOVIS (which uses ESM), each current patch is aligned to its previous
    patch by Gauss-Newton on the translation d (Lucas-Kanade), all matches at once:

        min_d  sum_patch ( I_cur(x + d) - mean - T(x) )^2,   T = previous patch minus its mean,

    sampling I_cur bilinearly. The 3D point follows from the depth interpolated at the new
    position. `previous` and `current` are aligned row by row (matched pairs); returns the refined
    current features and a mask of matches that converged near the corner and kept a valid depth.
    """
    pixels = current.pixels.copy()
    points = current.points.copy()
    valid = np.ones(len(current), dtype=bool)
    offsets = np.arange(-patch_radius, patch_radius + 1, dtype=np.float32)
    dv, du = (grid.ravel() for grid in np.meshgrid(offsets, offsets, indexing="ij"))
    for level in np.unique(current.levels):
        rows = np.flatnonzero(current.levels == level)
        intensity = current_levels[level].intensity.astype(np.float32)
        grad_u, grad_v = _central_differences(intensity)
        start = current.pixels[rows]
        shift = np.zeros_like(start)
        template = previous.descriptors[rows]
        for _ in range(_SUBPIXEL_ITERATIONS):
            map_u = (start[:, 0] + shift[:, 0])[:, None].astype(np.float32) + du
            map_v = (start[:, 1] + shift[:, 1])[:, None].astype(np.float32) + dv
            patch, gu, gv = (
                cv2.remap(image, map_u, map_v, cv2.INTER_LINEAR).astype(np.float64)
                for image in (intensity, grad_u, grad_v)
            )
            # Subtracting the mean is linear, so the Jacobian is the mean-free gradient.
            residual = patch - patch.mean(axis=1, keepdims=True) - template
            gu -= gu.mean(axis=1, keepdims=True)
            gv -= gv.mean(axis=1, keepdims=True)
            a, b, c = (gu * gu).sum(1), (gu * gv).sum(1), (gv * gv).sum(1)
            ru, rv = (gu * residual).sum(1), (gv * residual).sum(1)
            determinant = a * c - b * b
            # An edge or a flat patch constrains at most one direction: leave it where it is.
            solvable = determinant > 1e-6 * (a + c) ** 2 + 1e-12
            safe = np.where(solvable, determinant, 1.0)
            step = np.stack([-(c * ru - b * rv) / safe, -(a * rv - b * ru) / safe], axis=1)
            shift = np.clip(
                shift + np.where(solvable[:, None], step, 0.0), -_SUBPIXEL_REACH, _SUBPIXEL_REACH
            )
        # A patch that slid to the edge of its reach locked onto something else: drop the match.
        converged = np.abs(shift).max(axis=1) < _SUBPIXEL_REACH
        refined = start + shift
        base = refined * 2.0**level  # level-0 position, where the depth is read (see detection)
        depth = _interpolate_depth(current_levels[0].depth, base)
        pixels[rows] = refined
        points[rows] = _backproject_points(base, depth, camera)
        valid[rows] = converged & (depth > 0)
    refined_features = Features(
        current.levels, pixels, points, current.descriptors, current.responses
    )
    return refined_features, valid


def _central_differences(image: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    kernel = np.array([[-0.5, 0.0, 0.5]], dtype=np.float32)
    return cv2.filter2D(image, -1, kernel), cv2.filter2D(image, -1, kernel.T)


def _interpolate_depth(depth: np.ndarray, pixels: np.ndarray) -> np.ndarray:
    """Bilinear depth where the 4 neighbours are valid and agree, else the nearest pixel's."""
    u0 = np.floor(pixels[:, 0]).astype(np.int64)
    v0 = np.floor(pixels[:, 1]).astype(np.int64)
    fu, fv = pixels[:, 0] - u0, pixels[:, 1] - v0
    corners = np.stack(
        [depth[v0, u0], depth[v0, u0 + 1], depth[v0 + 1, u0], depth[v0 + 1, u0 + 1]], axis=1
    ).astype(np.float64)
    weights = np.stack([(1 - fu) * (1 - fv), fu * (1 - fv), (1 - fu) * fv, fu * fv], axis=1)
    bilinear = (corners * weights).sum(axis=1)
    agree = (corners.min(axis=1) > 0) & (
        corners.max(axis=1) - corners.min(axis=1) <= _DEPTH_AGREEMENT * corners.max(axis=1)
    )
    nearest = depth[np.rint(pixels[:, 1]).astype(np.int64), np.rint(pixels[:, 0]).astype(np.int64)]
    return np.where(agree, bilinear, nearest.astype(np.float64))


# --------------------------------------------------------------------------------------------
# 4. Inliers: the greatest clique of the consistency graph
# --------------------------------------------------------------------------------------------


def consistency_graph(
    previous_points: np.ndarray, current_points: np.ndarray, tolerance: float
) -> np.ndarray:
    """(M, M) bool: matches i and j agree when | |P_i - P_j| - |C_i - C_j| | < tolerance.

    A rigid motion preserves distances, so two correct matches always agree (up to depth noise);
    a wrong match rarely agrees with many others. The diagonal is False.
    """
    previous_distance = cdist(previous_points, previous_points)
    current_distance = cdist(current_points, current_points)
    adjacency = np.abs(previous_distance - current_distance) < tolerance
    np.fill_diagonal(adjacency, False)
    return adjacency


def greatest_clique(adjacency: np.ndarray) -> np.ndarray:
    """Sorted indices of a maximal clique, grown greedily (Howard 2008, Huang et al. 2011).

    Finding the maximum clique is NP-hard; the greedy approximation starts from the node with the
    most consistent partners and repeatedly adds, among the nodes consistent with every member so
    far, the one consistent with the most other such candidates.
    """
    if len(adjacency) == 0:
        return np.zeros(0, dtype=np.int64)
    links = adjacency.astype(np.float32)
    start = int(np.argmax(links.sum(axis=1)))
    clique = [start]
    candidates = adjacency[start].copy()
    # support[i]: how many current candidates node i is consistent with. Kept up to date by
    # subtracting the columns of dropped candidates, which costs O(M^2) over the whole loop.
    support = links @ candidates
    while candidates.any():
        chosen = int(np.argmax(np.where(candidates, support, -1.0)))
        clique.append(chosen)
        dropped = candidates & ~adjacency[chosen]  # includes `chosen`: the diagonal is False
        candidates &= adjacency[chosen]
        support -= links[:, dropped].sum(axis=1)
    return np.sort(np.array(clique, dtype=np.int64))


# --------------------------------------------------------------------------------------------
# 5. Motion
# --------------------------------------------------------------------------------------------


def absolute_orientation(source: np.ndarray, target: np.ndarray) -> np.ndarray:
    """The rigid motion T minimising sum |target_i - T source_i|^2 (Horn 1987 / Umeyama 1991)."""
    source_mean, target_mean = source.mean(axis=0), target.mean(axis=0)
    covariance = (target - target_mean).T @ (source - source_mean)
    u, _, vt = np.linalg.svd(covariance)
    # The sign fix keeps a proper rotation when the best orthogonal matrix is a reflection.
    sign = np.diag([1.0, 1.0, np.sign(np.linalg.det(u @ vt)) or 1.0])
    pose = np.eye(4)
    pose[:3, :3] = u @ sign @ vt
    pose[:3, 3] = target_mean - pose[:3, :3] @ source_mean
    return pose


def reprojection_residuals(
    increment: np.ndarray,
    previous: Features,
    current: Features,
    camera: Intrinsics,
) -> np.ndarray:
    """(M, 4) reprojection errors in pixels of each feature's level, both directions.

    Columns 0-1: previous 3D points moved into the current camera and projected, minus the current
    features' pixels; columns 2-3: the same from current to previous. Pixels are compared in
    level-0 coordinates (u0 = 2^l u_l under the pyrDown convention) and scaled back by 2^-l so a
    coarse feature's quantisation counts as much as a fine one's.
    """
    scale = 2.0 ** current.levels[:, None]
    rotation, translation = increment[:3, :3], increment[:3, 3]
    # x R^T = (R x)^T row by row; the inverse motion is x -> R^T (x - t), i.e. (x - t) R.
    previous_in_current = (previous.points - translation) @ rotation
    current_in_previous = current.points @ rotation.T + translation
    forward = _project(previous_in_current, camera) - current.pixels * scale
    backward = _project(current_in_previous, camera) - previous.pixels * scale
    return np.concatenate([forward, backward], axis=1) / scale


def _project(points: np.ndarray, camera: Intrinsics) -> np.ndarray:
    # A point behind the camera projects far away instead of dividing by ~0 or flipping sign.
    z = np.maximum(points[:, 2], 1e-3)
    return np.stack(
        [camera.fx * points[:, 0] / z + camera.cx, camera.fy * points[:, 1] / z + camera.cy], 1
    )


def refine_motion(
    initial: np.ndarray, previous: Features, current: Features, camera: Intrinsics
) -> np.ndarray:
    """Minimise the two-way reprojection error over the twist xi of T = exp(xi) T_initial."""

    def residuals(xi: np.ndarray) -> np.ndarray:
        return reprojection_residuals(se3.exp(xi) @ initial, previous, current, camera).ravel()

    solution = least_squares(residuals, np.zeros(6), method="lm", xtol=1e-12, ftol=1e-12)
    refined = se3.exp(solution.x) @ initial
    refined[:3, :3] = se3.orthonormalize(refined[:3, :3])
    return refined


# --------------------------------------------------------------------------------------------
# The whole estimator
# --------------------------------------------------------------------------------------------


def estimate_motion(
    previous: PreprocessedFrame, current: PreprocessedFrame, camera: Intrinsics, config: FovisConfig
) -> FovisResult:
    """FOVIS between two preprocessed frames; ok=False (with a reason) when it cannot tell."""
    _check_frame(previous, camera, "previous")
    _check_frame(current, camera, "current")
    previous_features = detect_features(previous, camera, config)
    current_features = detect_features(current, camera, config)
    if min(len(previous_features), len(current_features)) < config.min_inliers:
        return _failure(
            f"too few FAST corners with depth ({len(previous_features)} previous, "
            f"{len(current_features)} current)"
        )

    rotation = np.eye(3)
    if config.initial_rotation:
        coarsest = len(previous.levels) - 1
        rotation = estimate_initial_rotation(
            previous.levels[coarsest].intensity,
            current.levels[coarsest].intensity,
            camera.at_level(coarsest),
        )
    predicted = predict_pixels(previous_features, rotation, camera)
    previous_index, current_index = match_features(
        previous_features, current_features, predicted, config.search_radius
    )
    matched_previous = previous_features.subset(previous_index)
    matched_current = current_features.subset(current_index)
    if config.subpixel_refinement and len(matched_current):
        matched_current, kept = refine_subpixel(
            matched_previous, matched_current, current.levels, camera, config.patch_radius
        )
        matched_previous, matched_current = (
            matched_previous.subset(kept),
            matched_current.subset(kept),
        )
    if len(matched_current) < config.min_inliers:
        return _failure(f"too few mutually consistent matches ({len(matched_current)})")

    adjacency = consistency_graph(
        matched_previous.points, matched_current.points, config.clique_tolerance
    )
    clique = greatest_clique(adjacency)
    if len(clique) < config.min_inliers:
        return _failure(f"too few matches in the consistency clique ({len(clique)})")
    inlier_previous, inlier_current = (
        matched_previous.subset(clique),
        matched_current.subset(clique),
    )

    # Closed form on 3D pairs, refined on reprojection; reject bad reprojections once, refine again.
    increment = absolute_orientation(inlier_current.points, inlier_previous.points)
    increment = refine_motion(increment, inlier_previous, inlier_current, camera)
    good = _reprojects_well(increment, inlier_previous, inlier_current, camera, config)
    if good.sum() < config.min_inliers:
        return _failure(
            f"too few matches reproject within {config.reprojection_threshold} px "
            f"({int(good.sum())} of {len(good)})"
        )
    inlier_previous, inlier_current = inlier_previous.subset(good), inlier_current.subset(good)
    increment = refine_motion(increment, inlier_previous, inlier_current, camera)
    inliers = int(
        _reprojects_well(increment, inlier_previous, inlier_current, camera, config).sum()
    )
    if inliers < config.min_inliers:
        return _failure(f"too few inliers after re-estimation ({inliers})")
    return FovisResult(increment=increment, ok=True, inliers=inliers)


def _reprojects_well(
    increment: np.ndarray,
    previous: Features,
    current: Features,
    camera: Intrinsics,
    config: FovisConfig,
) -> np.ndarray:
    errors = reprojection_residuals(increment, previous, current, camera).reshape(-1, 2, 2)
    return np.linalg.norm(errors, axis=2).max(axis=1) <= config.reprojection_threshold


def _failure(reason: str) -> FovisResult:
    return FovisResult(increment=np.eye(4), ok=False, reason=reason)


def _check_frame(frame: PreprocessedFrame, camera: Intrinsics, name: str) -> None:
    levels = getattr(frame, "levels", None)
    if not levels:
        raise TrackingError(f"FOVIS: the {name} frame has no pyramid levels")
    shape = np.shape(levels[0].intensity)
    if shape != (camera.height, camera.width) or np.shape(levels[0].depth) != shape:
        raise TrackingError(
            f"FOVIS: the {name} frame's level-0 images are {shape}, depth "
            f"{np.shape(levels[0].depth)}; the camera is {camera.height}x{camera.width}"
        )
