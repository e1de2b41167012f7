"""Camera trackers (paper sections IV and V): one estimator per module, one factory here.

    icp            KinectFusion frame-to-model ICP (icp.py)
    rgbd           Steinbruecker et al.'s dense RGB-D odometry, frame-to-frame (rgbd.py)
    icp+rgbd       both in one joint system per iteration (combined.py), the default
    fovis          sparse FAST-feature visual odometry (fovis.py)
    fovis/X        FOVIS switching (switching.py, paper V-A): X's increment unless FOVIS disagrees
                   about the translation length by more than mu; X starts from FOVIS's increment
                   (config.fovis.dense_from_fovis) or from the previous pose

Every tracker returns a TrackingResult. Failure is expected and never raises: a singular system,
too few correspondences, too small a fraction of inliers, or an implausible jump (config.tracking)
give ok=False with a one-line reason and a safe pose - by default the previous pose times the last
good increment (constant velocity), or the previous pose itself - and the pipeline does not fuse
that frame. Poses are never NaN.

"Increment" everywhere is the current camera in the previous camera's frame:
increment = inverse(previous_pose) @ current_pose.
"""

from __future__ import annotations

import sys
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np

from kintinuous_ref import se3
from kintinuous_ref.camera import Intrinsics
from kintinuous_ref.config import Config
from kintinuous_ref.errors import ConfigError
from kintinuous_ref.odometry import switching
from kintinuous_ref.odometry.combined import CombinedProblem as CombinedProblem
from kintinuous_ref.odometry.combined import icp_model_noise, icp_robust_kernel
from kintinuous_ref.odometry.icp import IcpProblem as IcpProblem
from kintinuous_ref.odometry.rgbd import RgbdProblem as RgbdProblem
from kintinuous_ref.odometry.solve import LinearSystem, implausible_motion
from kintinuous_ref.odometry.solve import refine as refine
from kintinuous_ref.preprocess import model_pyramid as model_pyramid
from kintinuous_ref.vocabulary import DEFAULT_METHOD as DEFAULT_METHOD  # importable from here
from kintinuous_ref.vocabulary import DENSE_METHODS, FALLBACKS, METHODS

if TYPE_CHECKING:
    from kintinuous_ref.odometry.fovis import FovisResult
    from kintinuous_ref.preprocess import PreprocessedFrame
    from kintinuous_ref.raycast import ModelPrediction


@dataclass
class TrackingResult:
    pose: np.ndarray  # camera-to-world estimate of the current frame (never NaN)
    ok: bool  # False: the pipeline does not fuse the frame
    reason: str = ""  # one line, '' when ok
    used: str = ""  # which estimator's increment was used, e.g. "icp+rgbd" or "fovis"
    # FOVIS switching (fovis/X) only: both estimates and the choice, for diagnosis
    switch: switching.SwitchDecision | None = None


class Tracker(Protocol):
    def track(
        self,
        previous: PreprocessedFrame,
        current: PreprocessedFrame,
        model: ModelPrediction | None,
        previous_pose: np.ndarray,
    ) -> TrackingResult: ...


class _Recovery:
    """Remembers the last good increment and builds the fallback pose of a failed frame."""

    def __init__(self, fallback: str) -> None:
        if fallback not in FALLBACKS:
            raise ConfigError(f"tracking.fallback must be one of {FALLBACKS}, got {fallback!r}")
        self.fallback = fallback
        self.last_increment = np.eye(4)

    def success(
        self,
        pose: np.ndarray,
        previous_pose: np.ndarray,
        used: str,
        switch: switching.SwitchDecision | None = None,
    ) -> TrackingResult:
        self.last_increment = se3.inverse(previous_pose) @ pose
        return TrackingResult(pose, True, "", used, switch)

    def failure(
        self,
        previous_pose: np.ndarray,
        reason: str,
        switch: switching.SwitchDecision | None = None,
    ) -> TrackingResult:
        if self.fallback == "constant-velocity":
            pose = previous_pose @ self.last_increment
        else:
            pose = previous_pose.copy()
        # Keep the failed frame's motion out of the next fallback: a second failure in a row
        # then holds the pose still instead of extrapolating a guess.
        self.last_increment = np.eye(4)
        return TrackingResult(pose, False, reason, "", switch)


def repeated_streams(
    previous: PreprocessedFrame | None, current: PreprocessedFrame
) -> tuple[bool, bool]:
    """(depth repeated, colour repeated): which images equal the previous frame's bit for bit.

    Real sensors drop frames and repeat the last image, each stream on its own: in 7-Scenes
    redkitchen the colour of 16 and the depth of 17 of the 300 frames (from frame 222 on) equal
    their predecessors, both at once in 12. A repeated image is stale: it says "no motion"
    whatever the camera did. For the photometric cost it is also degenerate: at the initial
    estimate every residual is zero up to float rounding, sigma' collapses to ~1e-13 and the
    robust weights 1 / (sigma' + |r|) span up to twelve orders of magnitude. On redkitchen at
    320x240 that made icp+rgbd's joint system numerically singular at 7 repeats (and only
    there), and the constant-velocity fallback then added motion that never happened.
    """
    if previous is None:
        return False, False
    # Full-resolution depth and intensity: what every dense cost reads (the coarser levels and
    # the gradients are computed from them).
    before, now = previous.levels[0], current.levels[0]
    if not np.any(now.depth > 0):
        # Nothing measured twice is not a repeat: let tracking fail on it as on any blind frame.
        return False, False
    return (
        np.array_equal(before.depth, now.depth),
        np.array_equal(before.intensity, now.intensity),
    )


def stale_input(method: str, depth_repeated: bool, colour_repeated: bool) -> str:
    """'' when `method` has a fresh image to measure the motion with, else why it has none:
    RGB-D needs a new colour image, ICP a new depth image, ICP+RGB-D either (with one stale
    stream it tracks on the other alone)."""
    if depth_repeated and colour_repeated:
        return "the colour and depth images repeat the previous frame's: no new measurement"
    if colour_repeated and method == "rgbd":
        return "the colour image repeats the previous frame's: no new photometric measurement"
    if depth_repeated and method == "icp":
        return "the depth image repeats the previous frame's: no new geometric measurement"
    return ""


def is_repeated_frame(previous: PreprocessedFrame | None, current: PreprocessedFrame) -> bool:
    """True when both the depth and the colour image repeat the previous frame's."""
    return all(repeated_streams(previous, current))


def fovis_images(frame: PreprocessedFrame) -> PreprocessedFrame:
    """What FOVIS reads of a frame (every level's depth and intensity) as NumPy arrays: the
    reference's frames are on the host, so the frame itself."""
    return frame


class Systems(Protocol):
    """What the trackers compute with: the per-frame problems of each dense estimator, the model
    pyramid ICP reads, the coarse-to-fine solver, the stale-stream test and FOVIS's host images.

    This package is the reference's own (the module kintinuous_ref.odometry has each member);
    a fast backend's odometry stage module is its own, with the frames and maps where that
    backend keeps them (make_tracker there passes it here). Every member has the signature of
    this package's namesake:

    - IcpProblem(current_levels, model_levels, model_pose, ...) and RgbdProblem(previous_levels,
      current_levels, previous_pose, ...): icp.py's and rgbd.py's; an instance has
      system(level, pose) -> LinearSystem and inlier_fraction(pose, level=0) -> float.
    - CombinedProblem: combined.py's, with from_config(icp, rgbd, config.combined) and the
      `icp` and `rgbd` it sums (a tracker drops to one of them when the other's stream is
      stale).
    - A fast backend's problems are these classes over its own functions, which they name as
      class attributes: RgbdProblem's prepare_level, rgbd_system and stage (where an image goes
      before they read it), CombinedProblem's joint_system; its IcpProblem keeps the
      reference's arguments, checks and caches and computes each level's system itself.
    - model_pyramid(vertices, normals, levels): kintinuous_ref.preprocess's.
    - refine(pose, system_at, iterations, min_count, converged, step): solve.py's.
    - repeated_streams(previous, current) and fovis_images(frame): this module's.
    - estimate_dense(tracker, previous, current, model, previous_pose, start_pose): this
      module's, the steps of one dense estimate over the members above; the cuda backend's runs
      the same steps on the device and waits for it once a frame. Both start Gauss-Newton at
      `start_pose` (None: the previous pose), with the previous pose kept as RGB-D's reference
      and the jump check's origin.
    """

    IcpProblem: Callable[..., Any]
    RgbdProblem: Callable[..., Any]
    CombinedProblem: Any

    def model_pyramid(self, vertices: Any, normals: Any, levels: int) -> list[tuple[Any, Any]]:
        """The raycast maps downsampled as the current frame's pyramid (ICP's model levels)."""
        ...

    def refine(
        self,
        pose: np.ndarray,
        system_at: Callable[[int, np.ndarray], LinearSystem],
        iterations: Sequence[int],
        min_count: int = 6,
        converged: float = ...,
        step: tuple[Callable, Callable] | None = None,
    ) -> tuple[np.ndarray, str]:
        """Coarse-to-fine Gauss-Newton (solve.refine)."""
        ...

    def repeated_streams(
        self, previous: PreprocessedFrame | None, current: PreprocessedFrame
    ) -> tuple[bool, bool]:
        """(depth repeated, colour repeated), compared where the frames are kept."""
        ...

    def fovis_images(self, frame: PreprocessedFrame) -> PreprocessedFrame:
        """The frame's depth and intensity of every level as NumPy arrays, for FOVIS."""
        ...

    def estimate_dense(
        self,
        tracker: DenseTracker,
        previous: PreprocessedFrame,
        current: PreprocessedFrame,
        model: ModelPrediction | None,
        previous_pose: np.ndarray,
        start_pose: np.ndarray | None = None,
    ) -> tuple[np.ndarray, str]:
        """(pose, '') or (pose so far, why it failed): estimate_dense's steps."""
        ...


def estimate_dense(
    tracker: DenseTracker,
    previous: PreprocessedFrame,
    current: PreprocessedFrame,
    model: ModelPrediction | None,
    previous_pose: np.ndarray,
    start_pose: np.ndarray | None = None,
) -> tuple[np.ndarray, str]:
    """One dense estimate over the tracker's systems, its inputs checked (DenseTracker.estimate):
    the stale-stream test, the frame's problem, coarse-to-fine Gauss-Newton from `start_pose`
    (None: the previous pose, the paper's initial estimate), then the inlier and jump checks at
    the estimate. The previous pose stays RGB-D's reference frame and the origin of the jump
    check whatever the start. (pose, '') or (pose so far, why)."""
    systems = tracker.systems
    depth_repeated, colour_repeated = systems.repeated_streams(previous, current)
    stale = stale_input(tracker.method, depth_repeated, colour_repeated)
    if stale:
        # Nothing new to measure the motion with: a failure (the fallback pose, the frame not
        # fused), never a silently frozen pose.
        return previous_pose.copy(), stale
    problem = tracker.problem(previous, current, model, previous_pose)
    if isinstance(problem, systems.CombinedProblem) and (depth_repeated or colour_repeated):
        # One stream is stale: track on the fresh one alone for this frame.
        problem = problem.icp if colour_repeated else problem.rgbd
    tracking = tracker.config.tracking
    start = previous_pose if start_pose is None else start_pose
    pose, reason = systems.refine(
        np.array(start, dtype=np.float64),
        problem.system,
        tracker.iterations,
        tracking.min_correspondences,
        tracking.converged_step,
    )
    if reason:
        return pose, reason
    level, least = tracker.finest_level, tracking.min_inlier_fraction
    if isinstance(problem, systems.CombinedProblem):
        # Whether either term reaches the least fraction is all the check asks.
        fraction = problem.inlier_fraction(pose, level, enough=least)
    else:
        fraction = problem.inlier_fraction(pose, level)
    return pose, tracker.check_estimate(pose, previous_pose, fraction)


def _reference_systems() -> Systems:
    """This package itself: its module has every member of Systems."""
    return sys.modules[__name__]  # type: ignore[return-value]


class DenseTracker:
    """ICP, RGB-D or ICP+RGB-D: coarse-to-fine Gauss-Newton from the previous pose."""

    def __init__(
        self, method: str, config: Config, camera: Intrinsics, systems: Systems | None = None
    ) -> None:
        """`systems` builds and solves the normal equations (Systems: a fast backend's odometry
        module); None: the reference's own."""
        if method not in DENSE_METHODS:
            raise ConfigError(f"unknown dense odometry {method!r}; choose from {DENSE_METHODS}")
        self.method = method
        self.config = config
        self.camera = camera
        self.recovery = _Recovery(config.tracking.fallback)
        self.systems = systems if systems is not None else _reference_systems()

    @property
    def finest_level(self) -> int:
        """The finest pyramid level with iterations, where the inlier check looks: 0, or 1 with
        the fast-odometry setting (config.fast_odometry), which skips full resolution."""
        return next((level for level, count in enumerate(self.iterations) if count > 0), 0)

    @property
    def model_stride(self) -> int:
        """The pixel stride of the model prediction this tracker reads (raycast's `stride`):
        ICP at levels >= l reads only the pixels (2^l u, 2^l v) of it (model_pyramid)."""
        return 2**self.finest_level if self.method != "rgbd" else 1

    @property
    def iterations(self) -> tuple[int, ...]:
        if self.method == "icp":
            return tuple(self.config.icp.iterations)
        if self.method == "rgbd":
            return tuple(self.config.rgbd.iterations)
        return tuple(self.config.rgbd.combined_iterations)

    def problem(
        self,
        previous: PreprocessedFrame,
        current: PreprocessedFrame,
        model: ModelPrediction | None,
        previous_pose: np.ndarray,
    ) -> IcpProblem | RgbdProblem | CombinedProblem:
        """This frame's problem for the tracker's method, built from its systems."""
        levels = len(self.iterations)
        icp = rgbd = None
        if self.method in ("icp", "icp+rgbd"):
            icp = self.systems.IcpProblem(
                current.levels,
                self.systems.model_pyramid(model.vertices, model.normals, levels),
                model.pose,
                self.config.icp.distance_threshold,
                self.config.icp.angle_threshold_deg,
                icp_robust_kernel(self.method, self.config),
                self.config.icp.robust_noise,
                icp_model_noise(self.method, self.config),
            )
        if self.method in ("rgbd", "icp+rgbd"):
            rgbd = self.systems.RgbdProblem(
                previous.levels,
                current.levels,
                previous_pose,
                self.config.rgbd.min_gradient,
                self.config.rgbd.max_depth_change,
                self.config.rgbd.max_depth,
                self.config.rgbd.gradient,
            )
        if icp is not None and rgbd is not None:
            return self.systems.CombinedProblem.from_config(icp, rgbd, self.config.combined)
        return icp if icp is not None else rgbd

    def estimate(
        self,
        previous: PreprocessedFrame,
        current: PreprocessedFrame,
        model: ModelPrediction | None,
        previous_pose: np.ndarray,
        start_pose: np.ndarray | None = None,
    ) -> tuple[np.ndarray, str]:
        """(pose, '') or (best pose so far, reason for failure); never raises on bad data.
        `start_pose`: where Gauss-Newton starts (None: the previous pose)."""
        needs_model = self.method != "rgbd"
        if needs_model and model is None:
            return previous_pose, "no model prediction to track against"
        levels = len(self.iterations)
        for name, frame in (("previous", previous), ("current", current)):
            if frame is not None and len(frame.levels) < levels:
                return (
                    previous_pose,
                    f"{name} frame has {len(frame.levels)} pyramid levels, {levels} needed",
                )
        return self.systems.estimate_dense(
            self, previous, current, model, previous_pose, start_pose
        )

    def check_estimate(self, pose: np.ndarray, previous_pose: np.ndarray, fraction: float) -> str:
        """'' when a converged estimate with `fraction` inliers at the finest level stands, else
        why not: too few inliers, or an implausible jump (config.tracking)."""
        tracking = self.config.tracking
        least = tracking.min_inlier_fraction
        if fraction < least:
            return f"too few inliers ({100 * fraction:.1f}% < {100 * least:g}%)"
        return implausible_motion(
            se3.inverse(previous_pose) @ pose,
            tracking.max_translation_jump,
            tracking.max_rotation_jump_deg,
        )

    def track(
        self,
        previous: PreprocessedFrame,
        current: PreprocessedFrame,
        model: ModelPrediction | None,
        previous_pose: np.ndarray,
    ) -> TrackingResult:
        pose, reason = self.estimate(previous, current, model, previous_pose)
        if reason:
            return self.recovery.failure(previous_pose, f"{self.method}: {reason}")
        return self.recovery.success(pose, previous_pose, self.method)


class FovisTracker:
    """FOVIS alone, or FOVIS switching with a dense estimator (paper V-A), which starts from
    FOVIS's increment (or, where FOVIS failed, the last good one) when
    config.fovis.dense_from_fovis is on."""

    def __init__(
        self, method: str, config: Config, camera: Intrinsics, systems: Systems | None = None
    ) -> None:
        """`systems`: the dense half's (DenseTracker) and the host images FOVIS reads."""
        self.method = method
        self.config = config
        self.camera = camera
        self.systems = systems if systems is not None else _reference_systems()
        other = method.partition("/")[2]
        self.dense = DenseTracker(other, config, camera, self.systems) if other else None
        self.recovery = _Recovery(config.tracking.fallback)
        # (frame, its host images) of the last two frames: each frame is downloaded once, when
        # it is the current frame, and reused when it is the previous.
        self._on_host: list[tuple[PreprocessedFrame, PreprocessedFrame]] = []

    @property
    def model_stride(self) -> int:
        return self.dense.model_stride if self.dense is not None else 1

    def track(
        self,
        previous: PreprocessedFrame,
        current: PreprocessedFrame,
        model: ModelPrediction | None,
        previous_pose: np.ndarray,
    ) -> TrackingResult:
        tracking = self.config.tracking
        sparse = self.sparse_motion(previous, current)
        fovis_reason = sparse.reason or "failed"
        if sparse.ok:
            fovis_reason = implausible_motion(
                sparse.increment, tracking.max_translation_jump, tracking.max_rotation_jump_deg
            )
        fovis_ok = sparse.ok and not fovis_reason
        if self.dense is None:
            if not fovis_ok:
                return self.recovery.failure(previous_pose, f"fovis: {fovis_reason}")
            return self.recovery.success(previous_pose @ sparse.increment, previous_pose, "fovis")
        return self.switch(previous, current, model, previous_pose, sparse, fovis_ok, fovis_reason)

    def dense_start(self, fovis_increment: np.ndarray, fovis_ok: bool) -> np.ndarray | None:
        """The increment the dense estimate starts from with config.fovis.dense_from_fovis on:
        FOVIS's when it succeeded, else the last good frame's (constant velocity: a large step
        that FOVIS misses is still more like the one before than like no motion). Off: None,
        the previous pose (the paper's)."""
        if not self.config.fovis.dense_from_fovis:
            return None
        return fovis_increment if fovis_ok else self.recovery.last_increment

    def switch(
        self,
        previous: PreprocessedFrame,
        current: PreprocessedFrame,
        model: ModelPrediction | None,
        previous_pose: np.ndarray,
        sparse: FovisResult,
        fovis_ok: bool,
        fovis_reason: str,
    ) -> TrackingResult:
        """Paper V-A: the dense estimate, then FOVIS's increment or the dense one by the rule
        (switching.choose_increment_or_fallback); either alone when the other failed."""
        start = self.dense_start(sparse.increment, fovis_ok)
        start_pose = None if start is None else previous_pose @ start
        pose, dense_reason = self.dense.estimate(
            previous, current, model, previous_pose, start_pose
        )
        dense_increment = se3.inverse(previous_pose) @ pose
        decision = switching.SwitchDecision(
            sparse.increment if fovis_ok else None,
            None if dense_reason else dense_increment,
            np.eye(4) if start is None else start,
        )
        if dense_reason and not fovis_ok:
            return self.recovery.failure(
                previous_pose,
                f"fovis: {fovis_reason}; {self.dense.method}: {dense_reason}",
                decision,
            )
        if dense_reason:  # the dense estimator failed: FOVIS is all there is
            decision = decision.chose(switching.FOVIS)
            return self.recovery.success(
                previous_pose @ sparse.increment, previous_pose, "fovis", decision
            )
        fovis = self.config.fovis
        increment, chosen = switching.choose_increment_or_fallback(
            sparse.increment, fovis_ok, dense_increment, fovis.switch_threshold, fovis.switch_rule
        )
        used = "fovis" if chosen == switching.FOVIS else self.dense.method
        new_pose = previous_pose @ increment
        new_pose[:3, :3] = se3.orthonormalize(new_pose[:3, :3])
        return self.recovery.success(new_pose, previous_pose, used, decision.chose(chosen))

    def sparse_motion(self, previous: PreprocessedFrame, current: PreprocessedFrame) -> FovisResult:
        """FOVIS's estimate between the two frames, on host images (it runs on the CPU, as in
        the paper)."""
        from kintinuous_ref.odometry import fovis

        return fovis.estimate_motion(
            self._host_images(previous), self._host_images(current), self.camera, self.config.fovis
        )

    def _host_images(self, frame: PreprocessedFrame) -> PreprocessedFrame:
        for known, host in self._on_host:
            if known is frame:
                return host
        host = self.systems.fovis_images(frame)
        self._on_host = [*self._on_host[-1:], (frame, host)]  # this frame and the one before
        return host


def make_tracker(
    method: str, config: Config, camera: Intrinsics, systems: Systems | None = None
) -> Tracker:
    """The tracker for `method` (one of METHODS); `groundtruth` is the pipeline's business.
    `systems`: what it computes with (Systems), None: this package's own."""
    if method in DENSE_METHODS:
        return DenseTracker(method, config, camera, systems)
    if method in METHODS:
        return FovisTracker(method, config, camera, systems)
    raise ConfigError(f"unknown odometry method {method!r}; choose from {', '.join(METHODS)}")
