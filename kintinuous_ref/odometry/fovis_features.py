"""FOVIS' features and their matches (Huang et al. 2011; the paper's V-A): steps 1-3 of the
estimator that odometry/fovis.py describes and runs.

1. Features: FAST corners on each level of the Gaussian intensity pyramid, bucketed over the
   image, kept where the depth is valid and smooth over the patch; each described by its 9x9
   patch of intensities minus its mean.
2. Initial rotation: the coarsest images aligned by a 3-DOF rotation (from a grid of pans and
   tilts, coarse to fine), which predicts where each feature moves.
3. Matching: mutual nearest descriptors inside the search window around the prediction, refined to
   sub-pixel accuracy by aligning the patches.

fovis.py then finds the inliers among the matches (step 4) and the motion (step 5).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import cv2
import numpy as np

from kintinuous_ref import se3
from kintinuous_ref.camera import Intrinsics
from kintinuous_ref.config import FovisConfig

if TYPE_CHECKING:
    from kintinuous_ref.preprocess import PreprocessedFrame, PyramidLevel

# Sub-pixel refinement: Gauss-Newton steps, and how far (pixels) a patch may slide from its corner.
_SUBPIXEL_ITERATIONS = 6
_SUBPIXEL_REACH = 2
# Bilinear depth at a sub-pixel position only where the 4 neighbours agree to this fraction; across
# a depth edge the interpolated depth belongs to neither surface.
_DEPTH_AGREEMENT = 0.03
# An initial rotation estimate beyond this (radians, 20 degrees; redkitchen frames a second apart
# turn by up to 19) is taken for a failed alignment and ignored.
_MAX_INITIAL_ROTATION = 0.35
# The initial rotation starts on the coarsest level halved this many more times, down to images
# no smaller than _MIN_ROTATION_IMAGE_SIDE pixels a side (estimate_initial_rotation).
_INITIAL_ROTATION_HALVINGS = 2
_MIN_ROTATION_IMAGE_SIDE = 12
# The grid of pans and tilts (radians) the smallest images start from: up to 17 degrees each way,
# 2.5 degrees apart, less than a pixel of the 20x15 image, well inside Gauss-Newton's basin.
_PAN_TILT_RANGE = 0.3
_PAN_TILT_STEP = 0.0436


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
    """Rotation R (previous <- current) that best aligns two small images, coarse to fine.

    Gauss-Newton (rotation_from_images) converges only while the images are misaligned by a few
    pixels. At 30 Hz that holds on the coarsest pyramid level (80x60: a few degrees move it by a
    pixel or two), but between frames far apart in time a turn of 10-15 degrees moves the 80x60
    image by 15-20 pixels, and the estimate from the identity stops in a local minimum (on
    redkitchen every 20th frame it came back 4-9 degrees short and the search windows missed by
    80-120 px). So the images are halved up to _INITIAL_ROTATION_HALVINGS more times (to 20x15),
    the rotation is found there, where the same turn is 4-5 pixels, and each finer image starts
    from the coarser one's answer. Even there a turn together with a sideways step of 25 cm can
    put the identity outside the basin of the right minimum (on the synthetic `loop` path every
    15th frame Gauss-Newton went the wrong way), so the smallest images first pick the best of a
    grid of pans and tilts (best_pan_and_tilt) to start from.
    """
    previous_images = [previous_intensity.astype(np.float32)]
    current_images = [current_intensity.astype(np.float32)]
    cameras = [camera]
    for _ in range(_INITIAL_ROTATION_HALVINGS):
        if min(previous_images[-1].shape) < 2 * _MIN_ROTATION_IMAGE_SIDE:
            break
        previous_images.append(cv2.pyrDown(previous_images[-1]))
        current_images.append(cv2.pyrDown(current_images[-1]))
        cameras.append(cameras[-1].at_level(1))
    rotation = best_pan_and_tilt(previous_images[-1], current_images[-1], cameras[-1])
    for previous, current, level_camera in zip(
        previous_images[::-1], current_images[::-1], cameras[::-1], strict=True
    ):
        rotation = rotation_from_images(previous, current, level_camera, rotation, iterations)
    if se3.rotation_angle(rotation) > _MAX_INITIAL_ROTATION:
        return np.eye(3)
    return rotation


def best_pan_and_tilt(
    previous_intensity: np.ndarray, current_intensity: np.ndarray, camera: Intrinsics
) -> np.ndarray:
    """The rotation (previous <- current) about the camera's x and y axes, on a grid of
    _PAN_TILT_STEP up to _PAN_TILT_RANGE, that best aligns two small images.

    Each candidate warps the current image by the rotation's homography; the mean squared
    intensity difference over the pixels both images see decides. Candidates that leave less
    than half of the image in view are not considered (a small overlap can match by chance).
    The identity is a candidate, so nothing worse than no prior comes out of it.
    """
    previous = cv2.GaussianBlur(previous_intensity.astype(np.float32), (5, 5), 1.0)
    current = cv2.GaussianBlur(current_intensity.astype(np.float32), (5, 5), 1.0)
    height, width = previous.shape
    rays = camera.ray_directions().reshape(-1, 3).astype(np.float64)
    angles = np.arange(-_PAN_TILT_RANGE, _PAN_TILT_RANGE + 1e-9, _PAN_TILT_STEP)
    best, best_cost = np.eye(3), np.inf
    for tilt in angles:
        for pan in angles:
            rotation = se3.exp(np.array([tilt, pan, 0.0, 0.0, 0.0, 0.0]))[:3, :3]
            q = rays @ rotation  # R^T applied to each ray: previous frame -> current frame
            z = np.maximum(q[:, 2], 1e-6)
            u = camera.fx * q[:, 0] / z + camera.cx
            v = camera.fy * q[:, 1] / z + camera.cy
            valid = (q[:, 2] > 0) & (u >= 0) & (u <= width - 1) & (v >= 0) & (v <= height - 1)
            if valid.mean() < 0.5:
                continue
            warped = cv2.remap(
                current,
                u.reshape(height, width).astype(np.float32),
                v.reshape(height, width).astype(np.float32),
                cv2.INTER_LINEAR,
            ).ravel()
            cost = float(np.mean((warped[valid] - previous.ravel()[valid]) ** 2))
            if cost < best_cost:
                best, best_cost = rotation, cost
    return best


def rotation_from_images(
    previous_intensity: np.ndarray,
    current_intensity: np.ndarray,
    camera: Intrinsics,
    initial: np.ndarray,
    iterations: int = 10,
) -> np.ndarray:
    """Rotation R (previous <- current) aligning two images by Gauss-Newton, from `initial`.

    Under a pure rotation a previous pixel x maps to the current pixel pi(K W K^-1 x) with W = R^T
    (a homography, whatever the depth). W is updated as exp(delta) W, minimising
    sum (I_cur(pi(K W K^-1 x)) - I_prev(x))^2. Translation is ignored: at the coarsest pyramid
    level a few centimetres move the image by less than a pixel, while a few degrees move it by
    several. Returns `initial` when too few pixels overlap or the system is singular.
    """
    previous = cv2.GaussianBlur(previous_intensity.astype(np.float32), (5, 5), 1.0)
    current = cv2.GaussianBlur(current_intensity.astype(np.float32), (5, 5), 1.0)
    grad_x = cv2.Sobel(current, cv2.CV_32F, 1, 0, ksize=3) / 8.0
    grad_y = cv2.Sobel(current, cv2.CV_32F, 0, 1, ksize=3) / 8.0
    height, width = previous.shape
    rays = camera.ray_directions().reshape(-1, 3).astype(np.float64)
    reference = previous.ravel().astype(np.float64)
    rotation_cur_prev = np.asarray(initial, dtype=np.float64).T
    for _ in range(iterations):
        q = rays @ rotation_cur_prev.T
        u = camera.fx * q[:, 0] / q[:, 2] + camera.cx
        v = camera.fy * q[:, 1] / q[:, 2] + camera.cy
        # Keep one pixel from the border so the bilinear samples and gradients are genuine.
        valid = (q[:, 2] > 0) & (u >= 1) & (u <= width - 2) & (v >= 1) & (v <= height - 2)
        if valid.sum() < 20:
            return np.asarray(initial, dtype=np.float64)
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
            return np.asarray(initial, dtype=np.float64)
        rotation_cur_prev = se3.exp(np.concatenate([delta, np.zeros(3)]))[:3, :3] @ (
            rotation_cur_prev
        )
        if np.linalg.norm(delta) < 1e-6:
            break
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


def predict_pixels_with_motion(
    features: Features, increment: np.ndarray, camera: Intrinsics
) -> np.ndarray:
    """Where previous features appear in the current image under a full motion (level pixels).

    `increment` is previous <- current, so a previous point X is seen in the current camera at
    R^T (X - t); with each feature's own depth this also predicts the translation's parallax,
    which predict_pixels (a rotation alone) cannot.
    """
    rotation, translation = increment[:3, :3], increment[:3, 3]
    in_current = (features.points - translation) @ rotation
    z = np.maximum(in_current[:, 2], 1e-6)
    predicted = np.stack(
        [
            camera.fx * in_current[:, 0] / z + camera.cx,
            camera.fy * in_current[:, 1] / z + camera.cy,
        ],
        axis=1,
    )
    return predicted / 2.0 ** features.levels[:, None]


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
