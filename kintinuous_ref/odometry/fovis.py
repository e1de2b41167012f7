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
   window is centred where it is expected to move. It starts from the best of a grid of pans and
   tilts on the coarsest level halved twice more and refines coarse to fine, so that turns of
   10-17 degrees between frames far apart in time are found too.
3. Matching: for each feature, the descriptor nearest in L2 among the features of the other frame on
   the same level inside the search window; a match is kept only if it is the best in both
   directions (mutual consistency). The current feature's position is then refined to sub-pixel
   accuracy by aligning its patch to the previous one (Lucas-Kanade on the 2D shift). Once steps
   4-5 give a motion, the features are matched again in a small window around their positions
   predicted by that 6-DOF motion (estimate_motion says why).
4. Inliers: two matches are consistent when the rigid motion preserves the distance between their
   3D points. The largest set of mutually consistent matches (a clique of the consistency graph) is
   grown greedily from the best-connected match (Howard 2008).
5. Motion: absolute orientation (Horn / Umeyama, closed form) on the 3D inlier pairs, refined by
   minimising the reprojection error in both images; matches reprojecting worse than a threshold
   are rejected and the motion is estimated once more.

Steps 1-3 (features, initial rotation, matching) are in fovis_features.py, whose names this
module offers too; steps 4-5 and the estimator that runs all five are here.

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

from dataclasses import dataclass, replace
from typing import TYPE_CHECKING

import numpy as np
from scipy.optimize import least_squares
from scipy.spatial.distance import cdist

from kintinuous_ref import se3
from kintinuous_ref.camera import Intrinsics
from kintinuous_ref.config import FovisConfig
from kintinuous_ref.errors import TrackingError
from kintinuous_ref.odometry.fovis_features import (
    Features,
    bucket_strongest,
    detect_features,
    estimate_initial_rotation,
    fast_corners,
    match_features,
    patch_descriptors,
    predict_pixels,
    predict_pixels_with_motion,
    refine_subpixel,
    smooth_depth_mask,
)

if TYPE_CHECKING:
    from kintinuous_ref.preprocess import PreprocessedFrame

__all__ = [
    "Features",
    "FovisResult",
    "absolute_orientation",
    "bucket_strongest",
    "consistency_graph",
    "detect_features",
    "estimate_initial_rotation",
    "estimate_motion",
    "fast_corners",
    "greatest_clique",
    "match_features",
    "patch_descriptors",
    "predict_pixels",
    "predict_pixels_with_motion",
    "refine_motion",
    "refine_subpixel",
    "reprojection_residuals",
    "smooth_depth_mask",
]


@dataclass
class FovisResult:
    increment: np.ndarray  # 4x4 relative motion (previous <- current); identity when not ok
    ok: bool
    reason: str = ""
    inliers: int = 0
    # What each step kept, for diagnosis (benchmarks/large_motion.py): corners with depth in each
    # frame, mutually consistent matches and the consistency clique of the pass that decided.
    previous_features: int = 0
    current_features: int = 0
    matches: int = 0
    clique: int = 0


# Matching after a first motion estimate (estimate_motion): the window, pixels of the feature's
# level, around each feature's position predicted by that motion. The first estimate is good to a
# few pixels at the full resolution; the window holds that error and not much more, so that the
# nearest descriptor in it is rarely a wrong one.
_GUIDED_SEARCH_RADIUS = 6.0
# When the first pass finds no motion, its window is widened this many times and tried again:
# large motions leave a translation parallax the initial rotation does not predict.
_WIDE_SEARCH_FACTOR = 3.0

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
    """FOVIS between two preprocessed frames; ok=False (with a reason) when it cannot tell.

    Matching runs twice. The first pass searches around the positions the initial rotation
    predicts; its window (config.search_radius) must also hold the parallax of the translation,
    which the rotation cannot predict. At 30 Hz that parallax is a pixel or two, but between
    frames 0.3-1 s apart (10-20 cm) it is 20-40 px of the full image, beyond the window, and the
    few matches left were mostly wrong (on redkitchen every 20th frame, with the rotation as the
    only prediction: as few as 10 inliers, errors up to 8.5 cm). So, once the first pass gives a
    motion, each previous feature's 3D point is projected with that full 6-DOF motion, which
    predicts its position to within the first estimate's error, and the features are matched
    again in a window of _GUIDED_SEARCH_RADIUS px; the second estimate is kept when it has at
    least as many inliers. When the first pass fails, it is tried once more in a window
    _WIDE_SEARCH_FACTOR times larger before FOVIS gives up.
    """
    _check_frame(previous, camera, "previous")
    _check_frame(current, camera, "current")
    previous_features = detect_features(previous, camera, config)
    current_features = detect_features(current, camera, config)
    counts = {
        "previous_features": len(previous_features),
        "current_features": len(current_features),
    }
    if min(len(previous_features), len(current_features)) < config.min_inliers:
        return _failure(
            f"too few FAST corners with depth ({len(previous_features)} previous, "
            f"{len(current_features)} current)",
            **counts,
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
    pair = (previous_features, current_features, current, camera, config)
    first = _match_and_estimate(*pair, predicted, config.search_radius)
    if not first.ok:
        wide = _match_and_estimate(*pair, predicted, _WIDE_SEARCH_FACTOR * config.search_radius)
        if not wide.ok:
            return _with_counts(first, counts)
        first = wide
    guided_prediction = predict_pixels_with_motion(previous_features, first.increment, camera)
    guided = _match_and_estimate(*pair, guided_prediction, _GUIDED_SEARCH_RADIUS)
    best = guided if guided.ok and guided.inliers >= first.inliers else first
    return _with_counts(best, counts)


def _match_and_estimate(
    previous_features: Features,
    current_features: Features,
    current: PreprocessedFrame,
    camera: Intrinsics,
    config: FovisConfig,
    predicted: np.ndarray,
    search_radius: float,
) -> FovisResult:
    """Steps 3-5 with the features' predicted positions and a search window of search_radius."""
    previous_index, current_index = match_features(
        previous_features, current_features, predicted, search_radius
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
    matches = len(matched_current)
    if matches < config.min_inliers:
        return _failure(f"too few mutually consistent matches ({matches})", matches=matches)

    adjacency = consistency_graph(
        matched_previous.points, matched_current.points, config.clique_tolerance
    )
    clique = greatest_clique(adjacency)
    sizes = {"matches": matches, "clique": len(clique)}
    if len(clique) < config.min_inliers:
        return _failure(f"too few matches in the consistency clique ({len(clique)})", **sizes)
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
            f"({int(good.sum())} of {len(good)})",
            **sizes,
        )
    inlier_previous, inlier_current = inlier_previous.subset(good), inlier_current.subset(good)
    increment = refine_motion(increment, inlier_previous, inlier_current, camera)
    inliers = int(
        _reprojects_well(increment, inlier_previous, inlier_current, camera, config).sum()
    )
    if inliers < config.min_inliers:
        return _failure(f"too few inliers after re-estimation ({inliers})", **sizes)
    return FovisResult(increment=increment, ok=True, inliers=inliers, **sizes)


def _reprojects_well(
    increment: np.ndarray,
    previous: Features,
    current: Features,
    camera: Intrinsics,
    config: FovisConfig,
) -> np.ndarray:
    errors = reprojection_residuals(increment, previous, current, camera).reshape(-1, 2, 2)
    return np.linalg.norm(errors, axis=2).max(axis=1) <= config.reprojection_threshold


def _failure(reason: str, **sizes: int) -> FovisResult:
    return FovisResult(increment=np.eye(4), ok=False, reason=reason, **sizes)


def _with_counts(result: FovisResult, counts: dict[str, int]) -> FovisResult:
    return replace(result, **counts)


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
