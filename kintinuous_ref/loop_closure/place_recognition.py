"""Place recognition: is a new keyframe a place seen before, and where was the camera then?

Four stages, each of which can reject a candidate (the reason is counted, `Verdict.reason`):

1. **Appearance.** ORB descriptors of the new keyframe are matched against every older keyframe
   outside the recent window (those are the odometry's business), nearest neighbour by Hamming
   distance with Lowe's ratio test. The `candidates` keyframes with the most matches are
   verified; fewer than `min_matches` is "few matches". Direct matching costs one brute-force
   match per old keyframe (a few milliseconds each for 500 features); a bag of words (DBoW in
   Kintinuous) pays off only with thousands of keyframes.
2. **Geometry, sparse.** The matched keypoints' 3D points (from the depth) must agree on one
   rigid motion: RANSAC over minimal sets of 3 matches, each solved in closed form (Horn /
   Umeyama), keeping the motion with the most matches within `ransac_inlier_distance`; then
   re-solved on all its inliers. Too few inliers, or too small a share of the matches, is
   "geometry", unless the relative pose odometry gives the two keyframes is at hand (a tracked
   run) and `dense_from_odometry` is on (off by default): the dense stage then starts from that
   instead. Views 15-25 degrees apart keep too few ORB inliers although they overlap, and from
   a start within the odometry's drift the dense alignment ends where it ends from the true
   pose; the later checks judge the loop as they judge any other.
3. **Geometry and appearance, dense.** From that motion, the tracker's own ICP+RGB-D
   (odometry/combined.py: point-to-plane ICP and photometric error in one system) aligns the new
   keyframe to the old one, coarse to fine over the kept pyramid levels. ICP alone slid a few
   centimetres along the walls of the `revisit` scenario's start; the texture holds it.
   Accepted only if the point-to-plane RMSE is small, most of the points that the old view holds
   at the found pose found a partner ("dense": relative to the views' overlap, which a revisit
   from another angle keeps only in part, `Overlap`), and the intensities of the paired pixels
   agree once the exposure change between the views is taken off ("photometric"; the share
   asked for falls with the angle between the views). The last check is what separates two
   places built alike seen from the same angle (perceptual aliasing: identical furniture in two
   rooms aligns perfectly in geometry, but the walls around it differ in texture). The
   thresholds are calibrated on real revisits (calibration.py, docs/loop_closure.md).
4. **Plausibility.** The loop says how far odometry has drifted between the two keyframes; more
   than `max_correction` plus `max_correction_per_metre` of the path between them is not drift
   but another place ("implausible correction").

The motion found is the pose of the new keyframe in the old keyframe's camera frame: the loop
edge of the pose graph, with the covariance that the alignment's own final system states
(`alignment_information`, scaled to a calibrated number of effective pairs by `loop_covariance`):
a loop between views far apart, with fewer and worse-fitting pairs, weighs less than one
between near views.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from kintinuous_ref import se3
from kintinuous_ref.config import CombinedConfig, LoopClosureConfig, RgbdConfig, TrackingConfig
from kintinuous_ref.loop_closure.keyframes import FIRST_KEPT_LEVEL, Keyframe
from kintinuous_ref.odometry.combined import CombinedProblem, icp_scale, rgbd_scale
from kintinuous_ref.odometry.fovis import absolute_orientation
from kintinuous_ref.odometry.icp import IcpProblem
from kintinuous_ref.odometry.rgbd import RgbdProblem
from kintinuous_ref.odometry.solve import refine

REASONS = ("few matches", "geometry", "dense", "photometric", "implausible correction")


@dataclass
class Verdict:
    query: int  # node of the new keyframe
    match: int  # node of the old keyframe
    accepted: bool
    reason: str = ""  # one of REASONS when rejected
    matches: int = 0  # ratio-test ORB matches
    ransac_inliers: int = 0
    ransac_share: float | None = None  # RANSAC inliers per match
    icp_rmse: float | None = None  # metres
    icp_inlier_share: float | None = None  # paired points per valid point of the query
    visible_share: float | None = None  # query points the match's view holds (`Overlap`)
    icp_overlap_share: float | None = None  # paired points per visible point
    photometric_share: float | None = None
    correction: float | None = None  # metres the loop moves the new keyframe from odometry's pose
    relative: np.ndarray | None = None  # (4, 4) pose of the query in the match's camera frame
    # (6, 6) information of the dense pose per ICP pair, in the pose graph's residual
    # ([rotation, translation] of Z^-1 T_match^-1 T_query): `alignment_information`; the loop
    # edge's covariance is made from it by `loop_covariance`
    information: np.ndarray | None = None
    dense_pose: np.ndarray | None = None  # (4, 4) what the dense alignment found, accepted or not
    dense_start: str = "ransac"  # where the dense alignment started: "ransac" or "odometry"

    @property
    def dense_angle_deg(self) -> float | None:
        """Degrees between the two views' directions at the dense alignment's pose."""
        if self.dense_pose is None:
            return None
        return float(np.degrees(se3.rotation_angle(self.dense_pose[:3, :3])))

    def as_dict(self) -> dict:
        """The numbers for report.json (no arrays; a statistic that could not be measured, such
        as the RMSE of an alignment that failed, is None)."""
        numbers = {
            "query": self.query,
            "match": self.match,
            "accepted": self.accepted,
            "reason": self.reason or None,
            "matches": self.matches,
            "ransac_inliers": self.ransac_inliers,
            "ransac_share": self.ransac_share,
            "icp_rmse_m": self.icp_rmse,
            "icp_inlier_share": self.icp_inlier_share,
            "visible_share": self.visible_share,
            "icp_overlap_share": self.icp_overlap_share,
            "photometric_share": self.photometric_share,
            "correction_m": self.correction,
            "dense_start": self.dense_start,
        }
        return {
            key: None if isinstance(value, float) and not np.isfinite(value) else value
            for key, value in numbers.items()
        }


def match_descriptors(
    query: np.ndarray, train: np.ndarray, ratio: float
) -> tuple[np.ndarray, np.ndarray]:
    """(query indices, train indices) of ORB matches that pass Lowe's ratio test."""
    if len(query) < 2 or len(train) < 2:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    matcher = cv2.BFMatcher(cv2.NORM_HAMMING)
    pairs = matcher.knnMatch(query, train, k=2)
    good = [p[0] for p in pairs if len(p) == 2 and p[0].distance < ratio * p[1].distance]
    return (
        np.array([m.queryIdx for m in good], dtype=np.int64),
        np.array([m.trainIdx for m in good], dtype=np.int64),
    )


def ranked_candidates(
    query: Keyframe, older: list[Keyframe], config: LoopClosureConfig
) -> list[tuple[Keyframe, int]]:
    """The older keyframes (outside the recent window) with the most ORB matches, best first,
    at most `config.candidates`, with their match counts."""
    eligible = [k for k in older if query.node - k.node > config.recent_window]
    scored = [
        (k, len(match_descriptors(query.descriptors, k.descriptors, config.match_ratio)[0]))
        for k in eligible
    ]
    scored.sort(key=lambda item: -item[1])
    return scored[: config.candidates]


def ransac_rigid(
    source: np.ndarray,
    target: np.ndarray,
    iterations: int,
    threshold: float,
    rng: np.random.Generator,
) -> tuple[np.ndarray, np.ndarray]:
    """(T (4, 4), inlier mask) with target ~ T source for the most pairs within `threshold`."""
    count = len(source)
    best = np.zeros(count, dtype=bool)
    if count < 3:
        return np.eye(4), best
    for _ in range(iterations):
        sample = rng.choice(count, 3, replace=False)
        # Three nearly collinear points leave the rotation about their line free.
        spread = np.linalg.norm(np.cross(*(source[sample[1:]] - source[sample[0]])))
        if spread < 1e-4:
            continue
        motion = absolute_orientation(source[sample], target[sample])
        moved = source @ motion[:3, :3].T + motion[:3, 3]
        inliers = np.linalg.norm(moved - target, axis=1) < threshold
        if inliers.sum() > best.sum():
            best = inliers
    if best.sum() < 3:
        return np.eye(4), best
    motion = absolute_orientation(source[best], target[best])
    moved = source @ motion[:3, :3].T + motion[:3, 3]
    return motion, np.linalg.norm(moved - target, axis=1) < threshold


def dense_alignment(
    query: Keyframe,
    match: Keyframe,
    initial: np.ndarray,
    config: LoopClosureConfig,
    rgbd: RgbdConfig | None = None,
    combined: CombinedConfig | None = None,
) -> tuple[np.ndarray, str, float, float]:
    """The tracker's ICP+RGB-D (odometry/combined.py) of the query's kept levels against the
    match's, from `initial` (the query in the match's camera frame): (pose, failure reason or
    '', point-to-plane RMSE in metres, inlier share)."""
    rgbd = rgbd or RgbdConfig()
    combined = combined or CombinedConfig()
    levels = min(len(config.icp_iterations), len(query.levels), len(match.levels))
    icp, photometric = _problems(query, match, levels, rgbd)
    problem = CombinedProblem.from_config(icp, photometric, combined)
    tracking = TrackingConfig()
    pose, reason = refine(
        initial.copy(),
        problem.system,
        tuple(config.icp_iterations[:levels]),
        tracking.min_correspondences,
        tracking.converged_step,
    )
    if reason:
        return pose, reason, float("inf"), 0.0
    # The acceptance numbers use a tight association: the pairs a correct loop would give.
    tight = IcpProblem(query.levels[:1], [(match.levels[0].vertices, match.levels[0].normals)],
                       np.eye(4), distance_threshold=config.pair_distance,
                       angle_threshold_deg=20.0)  # fmt: skip
    system = tight.system(0, pose)
    rmse = float(np.sqrt(system.cost / system.count)) if system.count else float("inf")
    return pose, "", rmse, tight.inlier_fraction(pose, 0)


def _problems(
    query: Keyframe, match: Keyframe, levels: int, rgbd: RgbdConfig
) -> tuple[IcpProblem, RgbdProblem]:
    """ICP (query points against the match's surface) and RGB-D (the match's intensities
    warped into the query) over the first `levels` kept levels, both in the match's camera
    frame: the pose they refine is the query in the match's frame."""
    icp = IcpProblem(
        query.levels[:levels],
        [(m.vertices, m.normals) for m in match.levels[:levels]],
        np.eye(4),
        distance_threshold=0.1,
        angle_threshold_deg=20.0,
    )
    photometric = RgbdProblem(
        match.levels[:levels],
        query.levels[:levels],
        np.eye(4),
        rgbd.min_gradient[FIRST_KEPT_LEVEL:] or rgbd.min_gradient[-1:],
        rgbd.max_depth_change,
        rgbd.max_depth,
        rgbd.gradient,
    )
    return icp, photometric


def adjoint(pose: np.ndarray) -> np.ndarray:
    """Ad(T) (6, 6) for twists [omega, u]: T exp(xi) T^-1 = exp(Ad(T) xi)."""
    rotation, translation = pose[:3, :3], pose[:3, 3]
    out = np.zeros((6, 6))
    out[:3, :3] = rotation
    out[3:, 3:] = rotation
    out[3:, :3] = se3.skew(translation) @ rotation
    return out


def alignment_information(
    query: Keyframe, match: Keyframe, pose: np.ndarray, rgbd: RgbdConfig | None = None
) -> np.ndarray:
    """The information (6, 6) of a dense alignment's pose as its own final system states it,
    per geometric pair: at the finest kept level, J^T W J of the ICP pairs divided by their
    mean squared residual plus that of the RGB-D pixels divided by theirs (each term in units
    of its own noise), divided by the number of ICP pairs and expressed in the pose graph's
    residual. Per pair, so that it does not grow with the image size: the pairs' errors are
    correlated (neighbouring pixels, one sensor's distortion), and a loop is as certain as a
    few effective pairs (`loop_covariance`), not as all of them.

    The alignment's increment is a left perturbation in the match's frame, Z' = exp(xi) Z; the
    pose graph's residual of a loop edge is log(Z^-1 Z_graph), and at Z = exp(xi) Z_graph that
    is -Ad(Z^-1) xi to first order. So information H of xi is Ad(Z)^T H Ad(Z) of the residual
    (`residual_information`)."""
    icp, photometric = _problems(query, match, 1, rgbd or RgbdConfig())
    geometric, appearance = icp.system(0, pose), photometric.system(0, pose)
    information = np.zeros((6, 6))
    if geometric.count:
        information += geometric.A / icp_scale(geometric) ** 2
    if appearance.count:
        information += appearance.A / rgbd_scale(appearance) ** 2
    return residual_information(information / max(geometric.count, 1), pose)


def residual_information(information: np.ndarray, pose: np.ndarray) -> np.ndarray:
    """Information of a left increment xi of `pose` (Z' = exp(xi) Z) as information of the pose
    graph's residual log(Z^-1 Z_graph) = -Ad(Z^-1) xi: Ad(Z)^T H Ad(Z), symmetrised."""
    change = adjoint(pose)
    moved = change.T @ information @ change
    return (moved + moved.T) / 2


def loop_covariance(information: np.ndarray, config: LoopClosureConfig) -> np.ndarray:
    """The covariance (6, 6, [rotation, translation]) a loop edge is given from its alignment's
    per-pair information H (`alignment_information`): (`loop_effective_pairs` H)^-1, its
    standard deviation in every direction kept between the floor
    (`loop_sigma_floor_translation` / `_rotation_deg`: a noise-free synthetic alignment is not
    infinitely certain) and `loop_sigma_ceiling` times it (a direction the views hardly
    constrain is weak, not absent, and the matrix stays invertible). The bounds act on the
    eigenvalues of the information in floor units, so on the combined directions of rotation
    and translation that the alignment couples."""
    floor = np.array([np.radians(config.loop_sigma_floor_rotation_deg)] * 3
                     + [config.loop_sigma_floor_translation] * 3)  # fmt: skip
    information = np.asarray(information, dtype=np.float64) * config.loop_effective_pairs
    # in floor units u = D^-1 r, D = diag(floor): the information is D H D
    scaled = floor[:, None] * information * floor[None, :]
    values, vectors = np.linalg.eigh((scaled + scaled.T) / 2)
    values = np.clip(values, 1.0 / config.loop_sigma_ceiling**2, 1.0)
    in_floor_units = vectors @ np.diag(1.0 / values) @ vectors.T
    return floor[:, None] * in_floor_units * floor[None, :]


@dataclass
class Overlap:
    """Where the query's finest kept points land in the match's view at a pose."""

    valid: int  # query points with a vertex
    visible: np.ndarray  # (valid,) bool: in front of the match's camera, on a pixel with a vertex
    paired: np.ndarray  # (valid,) bool: visible and within the pairing distance in depth
    query_intensity: np.ndarray  # (paired,) the paired points' intensities in the query
    match_intensity: np.ndarray  # (paired,) and at the pixels they land on in the match
    match_gradient: np.ndarray  # (paired,) the match's intensity gradient there (per pixel)

    @property
    def visible_share(self) -> float:
        """The share of the query's points that the match's view holds at all: what a perfect
        alignment could pair (the view's overlap, less what the match has no depth for)."""
        return float(self.visible.mean()) if self.valid else 0.0

    @property
    def paired_share(self) -> float:
        return float(self.paired.mean()) if self.valid else 0.0


def overlap(query: Keyframe, match: Keyframe, pose: np.ndarray, pair_distance: float) -> Overlap:
    """The query's finest kept points moved by `pose` (the query in the match's camera frame)
    and projected into the match's finest kept level (nearest pixel)."""
    level_q, level_m = query.levels[0], match.levels[0]
    points = level_q.vertices.reshape(-1, 3)
    intensity = level_q.intensity.reshape(-1)
    valid = np.all(np.isfinite(points), axis=1)
    points, intensity = points[valid].astype(np.float64), intensity[valid]
    moved = points @ pose[:3, :3].T + pose[:3, 3]
    camera = level_m.camera
    z = moved[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        u = np.rint(camera.fx * moved[:, 0] / z + camera.cx)
        v = np.rint(camera.fy * moved[:, 1] / z + camera.cy)
    inside = (z > 0) & (u >= 0) & (u < camera.width) & (v >= 0) & (v < camera.height)
    u = np.where(inside, u, 0).astype(np.int64)
    v = np.where(inside, v, 0).astype(np.int64)
    surface = level_m.vertices[v, u, 2]
    visible = inside & np.isfinite(surface)
    with np.errstate(invalid="ignore"):
        paired = visible & (np.abs(surface - z) < pair_distance)
    gradient = np.hypot(level_m.intensity_dx[v, u], level_m.intensity_dy[v, u])
    return Overlap(
        valid=int(len(points)),
        visible=visible,
        paired=paired,
        query_intensity=intensity[paired].astype(np.float64),
        match_intensity=level_m.intensity[v, u][paired].astype(np.float64),
        match_gradient=gradient[paired].astype(np.float64),
    )


def exposure_fit(
    query_intensity: np.ndarray, match_intensity: np.ndarray, tolerance: float
) -> tuple[float, float]:
    """(gain, offset) with match ~ gain * query + offset: least squares over the pairs within
    `tolerance` of the current fit, from the median difference, three rounds. Real cameras
    change their exposure as they go; a gain and an offset over the whole view are what that
    change can do, and no more (a different texture does not become the same by it)."""
    gain, offset = 1.0, float(np.median(match_intensity - query_intensity))
    for _ in range(3):
        residual = match_intensity - (gain * query_intensity + offset)
        near = np.abs(residual) < tolerance
        if near.sum() < 10 or np.ptp(query_intensity[near]) < 1.0:
            break
        gain, offset = np.polyfit(query_intensity[near], match_intensity[near], 1)
        gain = float(np.clip(gain, *EXPOSURE_GAINS))
        offset = float(np.median(match_intensity[near] - gain * query_intensity[near]))
    return gain, offset


# The gains exposure_fit may find: auto exposure changes a Kinect's brightness by tens of per
# cent between views of one place, not by factors.
EXPOSURE_GAINS = (0.7, 1.4)


def photometric_share(
    paired: Overlap, tolerance: float, misregistration_px: float = 0.0, exposure: bool = False
) -> float:
    """Of the paired points, the share whose intensities agree: within `tolerance` levels plus
    what a misregistration of `misregistration_px` pixels makes of the match's gradient there
    (a texture edge a pixel off differs by its gradient), after an exposure change is taken off
    (`exposure_fit`) when `exposure`."""
    if not len(paired.query_intensity):
        return 0.0
    query, match = paired.query_intensity, paired.match_intensity
    allowed = tolerance + misregistration_px * paired.match_gradient
    gain, offset = exposure_fit(query, match, tolerance) if exposure else (1.0, 0.0)
    return float(np.mean(np.abs(match - (gain * query + offset)) < allowed))


def required_photometric_share(pose: np.ndarray, config: LoopClosureConfig) -> float:
    """The photometric share a true revisit seen from `pose` (the query in the match's camera
    frame) is asked for: less the further apart the two views' directions (LoopClosureConfig
    says why and by how much)."""
    degrees = float(np.degrees(se3.rotation_angle(pose[:3, :3])))
    required = config.min_photometric_share - config.photometric_share_per_degree * degrees
    return max(config.photometric_share_floor, required)


def verify(
    query: Keyframe,
    match: Keyframe,
    config: LoopClosureConfig,
    rng: np.random.Generator,
    matches: tuple[np.ndarray, np.ndarray] | None = None,
    every_check: bool = False,
    prior: np.ndarray | None = None,
    from_prior: bool = False,
) -> Verdict:
    """Stages 1-4 of the module docstring for one candidate pair. The first stage that fails
    rejects it and, unless `every_check` (for calibration: every statistic measured), the rest
    are not run. `prior` is the query in the match's camera frame as odometry has it: where the
    sparse stage finds too few inliers, the dense alignment starts from it instead of being
    refused (`dense_from_odometry`), and with `from_prior` it starts from it whatever the sparse
    stage found (to calibrate that start)."""
    iq, im = matches or match_descriptors(query.descriptors, match.descriptors, config.match_ratio)
    verdict = Verdict(query.node, match.node, False, matches=len(iq))

    def reject(reason: str) -> bool:
        verdict.reason = verdict.reason or reason
        return not every_check

    if len(iq) < config.min_matches and (reject("few matches") or len(iq) < 3):
        verdict.reason = "few matches"
        return verdict
    source, target = query.points[iq], match.points[im]
    both = np.all(np.isfinite(source), axis=1) & np.all(np.isfinite(target), axis=1)
    motion, inliers = ransac_rigid(
        source[both], target[both], config.ransac_iterations, config.ransac_inlier_distance, rng
    )
    verdict.ransac_inliers = int(inliers.sum())
    verdict.ransac_share = verdict.ransac_inliers / max(len(iq), 1)
    sparse = (
        verdict.ransac_inliers >= config.min_ransac_inliers
        and verdict.ransac_share >= config.min_ransac_share
    )
    if prior is not None and (from_prior or (not sparse and config.dense_from_odometry)):
        motion, verdict.dense_start = prior, "odometry"
    elif not sparse and reject("geometry"):
        return verdict
    pose, failure, rmse, share = dense_alignment(query, match, motion, config)
    verdict.dense_pose = pose
    if not failure:
        verdict.information = alignment_information(query, match, pose)
    seen = overlap(query, match, pose, config.pair_distance)
    verdict.icp_rmse, verdict.icp_inlier_share = rmse, share
    verdict.visible_share = seen.visible_share
    verdict.icp_overlap_share = share / seen.visible_share if seen.visible_share else 0.0
    if (
        failure
        or rmse > config.max_icp_rmse
        or verdict.icp_overlap_share < config.min_icp_overlap_share
        or verdict.visible_share < config.min_visible_share
    ) and reject("dense"):
        return verdict
    verdict.photometric_share = photometric_share(
        seen, config.photometric_tolerance, config.misregistration_px, exposure=True
    )
    if verdict.photometric_share < required_photometric_share(pose, config) and reject(
        "photometric"
    ):
        return verdict
    verdict.relative = pose
    odometry = se3.inverse(match.pose) @ query.pose
    verdict.correction = float(np.linalg.norm(odometry[:3, 3] - pose[:3, 3]))
    allowed = config.max_correction + config.max_correction_per_metre * abs(
        query.travelled - match.travelled
    )
    if verdict.correction > allowed and reject("implausible correction"):
        return verdict
    verdict.accepted = not verdict.reason
    return verdict


def naive_verify(
    query: Keyframe, match: Keyframe, config: LoopClosureConfig, rng: np.random.Generator
) -> bool:
    """Stages 1-2 only (appearance and sparse geometry), as a matcher without the dense and
    photometric checks would decide: for measuring what those checks add."""
    iq, im = match_descriptors(query.descriptors, match.descriptors, config.match_ratio)
    if len(iq) < config.min_matches:
        return False
    source, target = query.points[iq], match.points[im]
    both = np.all(np.isfinite(source), axis=1) & np.all(np.isfinite(target), axis=1)
    _, inliers = ransac_rigid(
        source[both], target[both], config.ransac_iterations, config.ransac_inlier_distance, rng
    )
    count = int(inliers.sum())
    return count >= config.min_ransac_inliers and count >= config.min_ransac_share * len(iq)
