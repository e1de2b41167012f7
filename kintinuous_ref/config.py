"""Every tunable of the system in one small tree of typed dataclasses.

Defaults are the values of the authors' public C++/CUDA code (Kintinuous, ElasticFusion)
and the paper; where the paper and the code disagree the field's comment
says which one the default follows. Dependent values (truncation from the volume size) are derived
in one place, `VolumeConfig.truncation`.
"""

from __future__ import annotations

import math
import numbers
import types
import typing
from dataclasses import dataclass, field, fields, is_dataclass, replace
from typing import Any

from kintinuous_ref.errors import ConfigError
from kintinuous_ref.vocabulary import (
    FALLBACKS,
    GRADIENTS,
    PLACEMENTS,
    ROBUST_KERNELS,
    SWITCH_RULES,
    WEIGHTINGS,
)


@dataclass(frozen=True)
class VolumeConfig:
    resolution: int = 256  # voxels per side (the paper: 512)
    size: float = 3.0  # side of the cube in metres (the paper: 6 m)
    max_weight: float = 128.0  # weight cap of the running average
    colour: bool = True  # keep a colour volume beside the TSDF (paper VI)
    shift_threshold: int = 14  # voxels from the basis before the volume shifts (1..16)
    # Kintinuous' cyclical buffer (moving_volume.py); False = a fixed KinectFusion volume
    moving: bool = True
    min_extract_weight: float = 8.0  # zero crossings lighter than this are not extracted
    # where the volume sits relative to the first camera (tsdf.volume_origin): "ahead" = the
    # camera at the centre of the face it looks through (KinectFusion), "centred" = at the centre
    placement: str = "ahead"
    truncation_distance: float | None = None  # metres; None = derived (see `truncation`)

    @property
    def voxel_size(self) -> float:
        return self.size / self.resolution

    @property
    def truncation(self) -> float:
        """max(0.01 m, side / 100): 0.06 m at 6 m, 0.03 m at 3 m; never below 2 voxels, since a
        thinner band leaves voxel columns with no negative sample and the raycast with holes
        (only coarse volumes such as 64^3 over 1 m are affected). `truncation_distance` wins."""
        if self.truncation_distance is not None:
            return self.truncation_distance
        return max(0.01, self.size / 100.0, 2.0 * self.voxel_size)

    def __post_init__(self) -> None:
        # A frozen config cannot change after it is made, so it is checked once, here: every
        # VolumeConfig that exists is valid, and its users (the CLI, the pipeline, each
        # backend's make_volume) need not check it again.
        self.validate()

    def validate(self) -> None:
        """Raise ConfigError (one line) for a field outside its range; runs when the config is
        made (``__post_init__``)."""
        if self.resolution < 8 or self.resolution > 1024:
            raise ConfigError(f"volume resolution must be in 8..1024, got {self.resolution}")
        if not self.size > 0:
            raise ConfigError(f"volume size must be positive, got {self.size} m")
        if not 1 <= self.shift_threshold <= 16:
            raise ConfigError(f"shift threshold must be 1..16 voxels, got {self.shift_threshold}")
        if self.truncation_distance is not None and not self.truncation_distance > 0:
            raise ConfigError(f"truncation must be positive, got {self.truncation_distance} m")
        if not self.max_weight >= 1:
            raise ConfigError(f"max weight must be >= 1, got {self.max_weight}")
        if self.placement not in PLACEMENTS:
            allowed = " or ".join(repr(word) for word in PLACEMENTS)
            raise ConfigError(f"volume placement must be {allowed}, got {self.placement!r}")


@dataclass(frozen=True)
class PreprocessConfig:
    bilateral_sigma_space: float = 4.5  # pixels
    bilateral_sigma_depth: float = 0.03  # metres
    bilateral_radius: int = 6  # 13x13 window
    pyramid_levels: int = 4
    pyramid_depth_cutoff: float = 0.09  # 3 sigma_depth: neighbours beyond it are ignored
    gradient_blur_sigma: float = 0.8  # 3x3 Gaussian before the Sobel (paper IV-A.1)
    max_depth: float = 6.0  # metres; farther measurements are dropped
    discontinuity_window: int = 7  # paper VI-B: 7x7 neighbourhood
    discontinuity_jump: float = 0.2  # metres
    discontinuity_max_bad: int = 5  # more bad neighbours than this: no colour update


@dataclass(frozen=True)
class IcpConfig:
    iterations: tuple[int, ...] = (10, 5, 4)  # finest to coarsest
    distance_threshold: float = 0.10  # metres
    angle_threshold_deg: float = 20.0
    # IRLS weights on the point-to-plane residuals of `icp` alone (odometry/icp.py): "huber"
    # (default: redkitchen 27.4 -> 23.7 mm, the synthetic scenes unchanged), "tukey" or "none"
    # (least squares, as the paper and KinectFusion). `icp+rgbd` takes its kernel from
    # combined.weighting ("huber" / "tukey"; least squares under the others).
    robust_kernel: str = "huber"
    # sigma, the spread of a good pair's residual the kernels are tuned to (Huber's k = 1.345
    # sigma, Tukey's c = 4.685 sigma): metres, fixed (odometry/icp.py says why not a median)
    robust_noise: float = 0.005
    # weigh each pair by the noise at its depth: the camera's axial noise and the model's
    # voxelisation, voxel / sqrt(12) (odometry/icp.py; corridor at 640x480 4.6 -> 2.9 mm,
    # redkitchen 23.7 -> 21.4 mm); for `icp` and the robust weightings of `icp+rgbd`. False:
    # every pair alike, as KinectFusion.
    depth_noise: bool = True


@dataclass(frozen=True)
class RgbdConfig:
    iterations: tuple[int, ...] = (10, 7, 7, 7)  # finest to coarsest, RGB-D alone
    combined_iterations: tuple[int, ...] = (10, 5, 4)  # when combined with ICP
    min_gradient: tuple[float, ...] = (12.0, 5.0, 3.0, 1.0)  # per level, finest to coarsest
    max_depth_change: float = 0.07  # d_s, metres: the authors' code's (the paper gives none)
    max_depth: float = 6.0
    # grad I in the Jacobian: "current" = current image at p (paper, Steinbruecker, OpenCV),
    # "warped" = previous image sampled at the warped p' (the cost's exact derivative)
    gradient: str = "current"


@dataclass(frozen=True)
class CombinedConfig:
    # the weight of the RGB-D term against the ICP term as `weighting` scales them: with "paper"
    # and its variants both terms are divided by their own noise, so 1 balances them, and this is
    # not the paper's w. The paper's w = 0.1 belongs to ICP in metres ("paper-metres" with 0.1),
    # the sum whose stationary point the authors' 100/10 weighting ("original-code") reaches
    # (odometry/combined.py; lesson 06 shows the two converge to the same poses)
    rgbd_weight: float = 1.0
    # "huber" (default): "degeneracy-aware" on Huber-weighted ICP rows (odometry/icp.py);
    # "tukey": the same with Tukey's biweight;
    # "degeneracy-aware": "paper", with ICP's say cut along the directions few of its pairs
    # observe (a corridor's length, a floor's plane), which RGB-D then decides;
    # "paper": A = J_icp^T J_icp / sigma_icp^2 + w J_rgbd^T J_rgbd (eq. 12-13, both terms in units
    # of their own noise); "information": RGB-D divided by its own noise too;
    # "paper-metres": the literal sum, ICP in metres;
    # "original-code" / "elasticfusion": A = A_rgbd + 100 A_icp, b = b_rgbd + 10 b_icp (the
    # public codes' scaling). docs/odometry.md measures each on every scene.
    weighting: str = "huber"
    original_code_icp_scale: float = 10.0  # "original-code": A_rgbd + s^2 A_icp, b_rgbd + s b_icp
    # "degeneracy-aware": along an ICP eigen-direction observed by a share s of its pairs below
    # this, ICP keeps s / threshold of its information (odometry/combined.py)
    degeneracy_threshold: float = 0.02


@dataclass(frozen=True)
class TrackingConfig:
    """Failure detection and recovery shared by every tracker (odometry/__init__.py)."""

    max_translation_jump: float = 0.3  # metres per frame; larger is implausible (a failure)
    max_rotation_jump_deg: float = 20.0  # degrees per frame
    min_correspondences: int = 50  # fewer pairs in any Gauss-Newton step: a failure
    # fewer ICP pairs per valid vertex (or RGB-D pairs per interest point) at the finest level
    min_inlier_fraction: float = 0.1
    # what a failed frame's pose becomes: "constant-velocity" (previous pose times the last good
    # increment) or "previous" (the previous pose)
    fallback: str = "constant-velocity"
    # a Gauss-Newton step shorter than this (twist norm, radians and metres together: 10 um)
    # ends its pyramid level early, so `iterations` are the most each level runs. On redkitchen
    # the later steps shrink ~3x each and stop mattering long before 10 um (docs/odometry.md).
    converged_step: float = 1e-5


@dataclass(frozen=True)
class FovisConfig:
    switch_threshold: float = 0.03  # mu of the switching rule (paper V-A), metres
    # "length" (the paper's rule) or "vector": on redkitchen every 20th frame fovis/icp+rgbd
    # tracks to 18.7 mm with "length" and 29.4 mm with "vector" (71.5 and 29.0 mm with the dense
    # half started from the previous pose), on every frame 22.2 mm with both
    # (docs/odometry.md, "FOVIS over large motions")
    switch_rule: str = "length"
    # Where the dense half of fovis/X starts its Gauss-Newton: True, FOVIS's increment when
    # FOVIS succeeded, so that the switching compares a dense refinement of FOVIS's motion with
    # FOVIS's own, and the last good frame's increment where FOVIS failed; False, the previous
    # pose (the dense trackers' start, section IV-A.3; the paper does not say where its
    # switched estimator starts). fovis/icp+rgbd on redkitchen every 20th frame: 18.7 mm with
    # True, 71.5 mm with False; every 30th 83.7 and 116.9 mm; on every frame 22.2 mm with both
    # (docs/odometry.md, "Starting the dense estimate from FOVIS")
    dense_from_fovis: bool = True
    fast_threshold: int = 20
    max_features: int = 600
    patch_radius: int = 4  # 9x9 descriptor patches
    clique_tolerance: float = 0.05  # metres: 3D distances preserved to within this
    feature_levels: int = 3  # pyramid levels searched for FAST corners (Huang et al.: 3)
    bucket_size: int = 80  # level-0 pixels per side of a bucket (Huang et al.: 80x80)
    search_radius: float = 16.0  # pixels of the feature's level around its predicted position
    initial_rotation: bool = True  # predict positions by aligning the coarsest images (rotation)
    subpixel_refinement: bool = True  # align each matched patch to sub-pixel accuracy
    reprojection_threshold: float = 1.5  # pixels of the feature's level; larger: outlier
    min_inliers: int = 10  # fewer: FOVIS reports failure
    patch_depth_variation: float = 0.10  # depth spread (fraction) over a patch: a silhouette


@dataclass(frozen=True)
class ColourConfig:
    angle_weighting: bool = True  # weight colour updates by cos(theta) = n_z (eq. 15)
    discontinuity_check: bool = True  # no colour update near depth edges (paper VI-B)
    max_weight: float = 255.0


@dataclass(frozen=True)
class LoopClosureConfig:
    """Loop closure with map deformation (loop_closure/, docs/loop_closure.md)."""

    # keyframes: a new one when the camera has moved this far or turned this much since the last
    # (Kintinuous samples a pose graph node per volume shift, about 0.2-0.4 m at its settings)
    keyframe_distance: float = 0.3  # metres
    keyframe_angle_deg: float = 15.0
    orb_features: int = 500  # ORB keypoints per keyframe (OpenCV's default)
    # the latest keyframes are the odometry's business: a loop needs this many between the two
    recent_window: int = 8
    candidates: int = 3  # best-matching older keyframes verified per new keyframe
    match_ratio: float = 0.8  # Lowe's ratio test on ORB Hamming distances
    # Thresholds below are calibrated on real revisits (benchmarks/loop_calibration.py, the
    # numbers in docs/loop_closure.md): redkitchen views of one place 15-45 cm and 15-27 degrees
    # apart keep only 18-77 ratio-test matches and 4-26 RANSAC inliers (22-46 % of the matches),
    # and the dense check is what tells a right alignment from a wrong one there.
    min_matches: int = 12  # fewer ratio-test matches: not a candidate
    # sparse 3D-3D RANSAC on the depth: a first cut, for the time the dense check costs. Wrong
    # motions reach 47 inliers and 43 % of the matches, right ones (of offset views) have as few
    # as 4 and 22 %; with these two cuts at 3 and 0 no more wrong candidates of the calibration
    # pass the dense and photometric checks. At 4 and 10 % the offset return at 160x120 closes
    # its offset loop (weighed by its alignment's covariance, the return error then falls), but
    # the tracked `twins` walk accepts a loop (a true one: two views of one wall 2.75 m apart),
    # so the cuts stay at 6 and 20 % (dense_from_odometry closes such loops another way)
    ransac_iterations: int = 300
    ransac_inlier_distance: float = 0.05  # metres between matched 3D points after alignment
    min_ransac_inliers: int = 6
    min_ransac_share: float = 0.2  # inliers per match
    # Where the sparse cut refuses a candidate, start the dense alignment from the relative pose
    # odometry gives the two keyframes instead: views 15-25 degrees apart keep too few ORB
    # inliers (redkitchen: 3-5 of 17-21 matches) although they overlap, and from that start
    # the alignment ends where it ends from the true pose (the dense, photometric and
    # plausibility checks and the pose graph's consistency test still judge the loop). Off:
    # with it the ATE rises in five of six measured runs, by 0.3-0.6 mm on redkitchen there
    # and back and 8.7 -> 11.2 mm on twins (the far loops' alignments are centimetres from the
    # ground truth; docs/loop_closure.md)
    dense_from_odometry: bool = False
    # After a closure, tracking keeps the moving volume's window and its coordinates, and a
    # running offset maps every later pose into corrected ones, the map staying in the
    # tracker's coordinates until its deformation (False, as the authors' implementation does:
    # the uncorrected trajectory is then the run without loop closure, bit for bit); or the
    # window is emptied into a slice and re-centred at the corrected pose (True), and tracking
    # starts again on a model of one frame. On redkitchen there and back at 160x120,
    # re-centred, the return error was 1.7-9.8 mm worse in four runs of five and the ATE
    # 0.7-2.3 mm worse in three; the `revisit` meshes are alike (6.5 mm from the true surface
    # either way; docs/loop_closure.md, "Tracking after a closure")
    recentre_on_closure: bool = False
    # dense refinement (the tracker's ICP+RGB-D of the two frames) and the acceptance test
    icp_iterations: tuple[int, ...] = (10, 10, 10)  # pyramid levels 1.., finest to coarsest
    # metres of point-to-plane residual over the matched pairs: right alignments of real views
    # 2-3 m deep reach 12 mm (Kinect noise there is about 1 cm per frame)
    max_icp_rmse: float = 0.015
    pair_distance: float = 0.03  # metres: a point of the new keyframe paired with the old's
    # Paired points per point of the new keyframe that the old keyframe's view holds at the
    # found pose (Overlap.visible_share), not per point of the new keyframe: a true revisit
    # from 15-27 degrees away shares only 42-66 % of its view, so the absolute share of a right
    # alignment falls to 0.24, while the relative one stays at 0.53-0.91; wrong alignments score
    # 0.00-0.17 on it
    min_icp_overlap_share: float = 0.35
    # a loop over less than this share of the new view constrains little (right: 0.42 and up)
    min_visible_share: float = 0.25
    # Photometric check, after the exposure change between the views is taken off (a gain and an
    # offset, place_recognition.exposure_fit: redkitchen's views differ by gains of 0.86-1.16
    # and offsets of up to 21 levels): paired pixels within this many levels agree
    photometric_tolerance: float = 20.0
    # pixels of misregistration allowed at texture edges, times the gradient there: none, as
    # 1-2 pixels raised the twins' share (0.71 to 0.76-0.80) as much as the real revisits'
    misregistration_px: float = 0.0
    # The share of agreeing pixels a true revisit reaches falls with the angle between the two
    # views (shading that depends on the view, resampling at another scale): 0.92-0.99 for the
    # same view, 0.78-0.83 at 5-7 degrees, 0.53-0.77 at 15-27 degrees. So the share asked for is
    # min_photometric_share less photometric_share_per_degree per degree between the views
    # (at the found pose), never below photometric_share_floor. Two identical bays in different
    # places (the synthetic `twins`) align at a few degrees and score 0.71, under the 0.8 asked
    # there; a wrong alignment is the dense check's to refuse.
    min_photometric_share: float = 0.85
    photometric_share_per_degree: float = 0.02
    photometric_share_floor: float = 0.5
    # a loop that moves the new keyframe further than this from where odometry put it (metres
    # plus a share of the path since the old keyframe) is not drift but a different place
    max_correction: float = 0.3
    max_correction_per_metre: float = 0.05
    # pose graph: standard deviations of the edges (odometry drifts ~1 cm and 0.5 degree per
    # 0.3 m keyframe step on the synthetic scenes); the loop sigmas only with
    # loop_covariance_from_alignment off (a verified loop as good as one step)
    odometry_sigma_translation: float = 0.01  # metres
    odometry_sigma_rotation_deg: float = 0.5
    loop_sigma_translation: float = 0.01
    loop_sigma_rotation_deg: float = 0.5
    # Loop edges take their covariance from their own dense alignment when this is on
    # (place_recognition.loop_covariance): the information its final system states per pair,
    # times loop_effective_pairs, so that a loop between views 24 cm and 11 degrees apart is
    # weighed by what its fewer, worse-fitting pairs say (3 times looser than one between near
    # views on redkitchen). Off: the fixed loop sigmas above.
    loop_covariance_from_alignment: bool = True
    # The pairs' errors are correlated (neighbouring pixels, one sensor's distortion): a real
    # alignment misses by what a handful of independent pairs would. Calibrated on redkitchen's
    # revisits against their ground truth (benchmarks/loop_calibration.py: the maximum
    # likelihood scale over the right candidates, docs/loop_closure.md)
    loop_effective_pairs: float = 3.5
    # standard deviations of a loop never below these (a noise-free synthetic alignment), nor
    # above loop_sigma_ceiling times them (a direction the views hardly constrain)
    loop_sigma_floor_translation: float = 0.001  # metres
    loop_sigma_floor_rotation_deg: float = 0.05
    loop_sigma_ceiling: float = 100.0
    # loop edges are scaled by dynamic covariance scaling (Agarwal et al., ICRA 2013), the closed
    # form of switchable constraints: s = min(1, 2 phi / (phi + chi^2)), phi = 1 / sigma^2
    switch_prior_sigma: float = 1.0
    # a new loop is kept when, solved with it, no edge disagrees by more than this many sigmas
    # (a true loop spreads its drift over many edges: under 1 sigma each on `revisit`)
    loop_consistency_sigmas: float = 5.0
    # deformation graph (Sumner et al. 2007): nodes this far apart on the mesh, k nodes per vertex
    node_spacing: float = 0.25  # metres
    node_neighbours: int = 4  # graph edges per node, and nodes that move each vertex
    time_scale: float = 0.005  # metres of distance per frame between a vertex and a node
    rotation_weight: float = 1.0  # Sumner et al.'s E_rot, E_reg, E_con weights
    regularisation_weight: float = 10.0
    constraint_weight: float = 100.0
    constraint_spread: float = 0.5  # metres: the cross of pinned points around each keyframe


@dataclass(frozen=True)
class Config:
    volume: VolumeConfig = field(default_factory=VolumeConfig)
    preprocess: PreprocessConfig = field(default_factory=PreprocessConfig)
    icp: IcpConfig = field(default_factory=IcpConfig)
    rgbd: RgbdConfig = field(default_factory=RgbdConfig)
    combined: CombinedConfig = field(default_factory=CombinedConfig)
    fovis: FovisConfig = field(default_factory=FovisConfig)
    colour: ColourConfig = field(default_factory=ColourConfig)
    tracking: TrackingConfig = field(default_factory=TrackingConfig)
    loop_closure: LoopClosureConfig = field(default_factory=LoopClosureConfig)

    def validate(self) -> Config:
        """Return this config after checking every field's value (`check_values`); the volume's
        own ranges are checked when a VolumeConfig is made (VolumeConfig.__post_init__)."""
        check_values(self)
        return self


def fast_odometry(config: Config) -> Config:
    """`config` with the finest pyramid level skipped by every dense estimator (0 iterations
    there; the inlier check looks at the next level, and the pipeline raycasts only the quarter
    of the pixels that level reads): the original code's "fast odometry" option, for CPUs
    (docs/benchmarks.md and the archive it links to measure its accuracy cost)."""

    def skip_finest(iterations: tuple[int, ...]) -> tuple[int, ...]:
        return (0, *iterations[1:])

    return replace(
        config,
        icp=replace(config.icp, iterations=skip_finest(config.icp.iterations)),
        rgbd=replace(
            config.rgbd,
            iterations=skip_finest(config.rgbd.iterations),
            combined_iterations=skip_finest(config.rgbd.combined_iterations),
        ),
    )


# Keys that older configuration files may name, and the key that replaces each: one translation
# limit, tracking's, holds for every tracker.
RENAMED_KEYS = {"rgbd.max_translation_jump": "tracking.max_translation_jump"}


def with_overrides(config: Any, overrides: dict[str, Any], _prefix: str = "") -> Any:
    """A copy of a config tree with dotted keys replaced: {"volume.size": 6.0}. Each value is
    checked against its field's type (`checked_value`); a bad key or value is a ConfigError that
    names the key, what was expected and what was found."""
    names = {f.name: f for f in fields(config)}
    grouped: dict[str, dict[str, Any]] = {}
    direct: dict[str, Any] = {}
    for key, value in overrides.items():
        if not isinstance(key, str) or not key:
            raise ConfigError(f"configuration keys are dotted names, got {key!r}")
        if _prefix + key in RENAMED_KEYS:
            renamed = RENAMED_KEYS[_prefix + key]
            raise ConfigError(f"configuration key {_prefix + key!r} is now {renamed!r}")
        head, _, rest = key.partition(".")
        if head not in names:
            raise ConfigError(f"unknown configuration key {_prefix + key!r}")
        if rest:
            grouped.setdefault(head, {})[rest] = value
        else:
            direct[head] = value
    hints = typing.get_type_hints(type(config))
    for head, value in list(direct.items()):
        if is_dataclass(getattr(config, head)) and value == {}:
            del direct[head]  # an empty section changes nothing
        elif is_dataclass(getattr(config, head)):
            keys = ", ".join(f.name for f in fields(getattr(config, head)))
            raise ConfigError(
                f"{_prefix + head}: expected a section of keys ({keys}), found {_shown(value)}"
            )
        else:
            direct[head] = checked_value(_prefix + head, hints[head], value)
    for head, sub in grouped.items():
        child = getattr(config, head)
        if not is_dataclass(child):
            raise ConfigError(f"{_prefix + head!r} has no sub-keys")
        direct[head] = with_overrides(child, sub, f"{_prefix}{head}.")
    return replace(config, **direct)


# ----------------------------------------------------------------------------------------------
# Validation: every value is checked against the type its dataclass field declares. Numbers are
# finite and not negative (no field of the tree has a meaningful negative value); tuples hold at
# least one such number; the text fields take one of a few words (CHOICES).


# The words each text field accepts (kintinuous_ref.vocabulary).
CHOICES: dict[str, tuple[str, ...]] = {
    "volume.placement": PLACEMENTS,
    "rgbd.gradient": GRADIENTS,
    "combined.weighting": WEIGHTINGS,
    "icp.robust_kernel": ROBUST_KERNELS,
    "tracking.fallback": FALLBACKS,
    "fovis.switch_rule": SWITCH_RULES,
}


def _shown(value: Any) -> str:
    """A found value for a message: short, one line."""
    text = repr(value)
    text = text if len(text) <= 60 else text[:57] + "..."
    return f"{type(value).__name__} {text}"


def _number(key: str, kind: type, value: Any) -> int | float:
    """An int or float field's value: finite, >= 0; an integral float is accepted for an int."""
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        what = "an integer" if kind is int else "a number"
        raise ConfigError(f"{key}: expected {what} >= 0, found {_shown(value)}")
    if not math.isfinite(value):
        raise ConfigError(f"{key}: expected a finite number, found {value!r}")
    if kind is int:
        if not isinstance(value, numbers.Integral) and value != int(value):
            raise ConfigError(f"{key}: expected an integer >= 0, found {_shown(value)}")
        value = int(value)
    else:
        value = float(value)
    if value < 0:
        raise ConfigError(f"{key}: expected a number >= 0, found {value!r}")
    return value


def checked_value(key: str, annotation: Any, value: Any) -> Any:
    """`value` as the field `key` of type `annotation` holds it (a list becomes a tuple, an
    integral number an int), or a ConfigError naming the key, what was expected and what was
    found."""
    if typing.get_origin(annotation) in (typing.Union, types.UnionType):
        options = [a for a in typing.get_args(annotation) if a is not type(None)]
        if value is None and len(options) < len(typing.get_args(annotation)):
            return None
        return checked_value(key, options[0], value)
    if annotation is bool:
        if not isinstance(value, bool):
            raise ConfigError(f"{key}: expected true or false, found {_shown(value)}")
        return value
    if annotation in (int, float):
        return _number(key, annotation, value)
    if annotation is str:
        choices = CHOICES.get(key)
        if not isinstance(value, str) or (choices is not None and value not in choices):
            expected = f"one of {', '.join(choices)}" if choices else "a word"
            raise ConfigError(f"{key}: expected {expected}, found {_shown(value)}")
        return value
    if typing.get_origin(annotation) is tuple:
        kind = typing.get_args(annotation)[0]
        what = "integers" if kind is int else "numbers"
        if not isinstance(value, list | tuple) or not value:
            raise ConfigError(
                f"{key}: expected a list of {what} >= 0 such as [10, 5, 4], found {_shown(value)}"
            )
        return tuple(_number(f"{key}[{i}]", kind, item) for i, item in enumerate(value))
    raise ConfigError(f"{key}: cannot be set")  # pragma: no cover - every field is typed above


def check_values(config: Any, _prefix: str = "") -> None:
    """Every field of a config tree against its declared type (ConfigError naming the first
    bad key): what the command line's options and a program's own Config(...) put there."""
    hints = typing.get_type_hints(type(config))
    for item in fields(config):
        value = getattr(config, item.name)
        if is_dataclass(value):
            check_values(value, f"{_prefix}{item.name}.")
        else:
            checked_value(_prefix + item.name, hints[item.name], value)
