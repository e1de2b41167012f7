"""The per-frame loop of the system as one "algorithm box" (paper III-V, docs/architecture.md).

    for each RGB-D frame:
        1. preprocess        metric depth, filters, pyramids, vertex/normal maps (IV-A.1)
        2. odometry          pose from the ground truth, or tracker.track(previous, current,
                             model, previous_pose) (IV, V); a failed frame is not fused
        3. moving volume     shift the cyclical buffer if the camera moved far enough; the
                             slices that leave are meshed and stored (III, Fig. 2)
        4. integrate         depth into the TSDF, colour into the colour volume (III, VI)
        5. raycast           the model seen from the new pose, for the next frame's ICP (III):
                             vertices and normals (the trackers read no model colour)
        6. record            pose and per-stage timings; report progress
    at the end: the rest of the volume becomes the last slice; the slices one mesh.

With a loop closer (loop_closure/closer.py), step 2 is followed by 2b: the closer sees every
pose, takes keyframes and looks for loops; when it closes one, tracking keeps its volume and
its coordinates, and the poses recorded from then on are moved by the correction
(`LoopCloser.in_map`; with `recentre_on_closure` the pose moves and the volume is re-centred
there instead). The final trajectory and map are corrected at the end (`trajectory`,
`LoopCloser.deform_map`).

The backend is a parameter: any kintinuous_ref.backend.Backend (the reference itself, the default,
or a fast backend found through the `kintinuous.backends` entry points). Its stage modules compute
each step, its tracker tracks, and state stays where it computes: `upload` puts each frame's two
images there once and `predict_surface` leaves the raycast maps there, so with cuda the frames,
maps and volume live in GPU memory for the whole run and only poses, the trackers' 6x6 systems
and the outputs cross to the host.

Volume placement and the tracker's start need the first pose: with ground-truth odometry it is
the ground truth; with a tracker it is the first ground-truth pose when the dataset has one (so
trajectories are comparable with it), else the identity.

Ctrl-C (KeyboardInterrupt), and SIGTERM or SIGHUP once `handle_signals` is in force (the command
line's), end the loop cleanly: the result holds the poses so far and the volume of what was
fused, with `interrupted` and `reason` set. With `capture_errors` an exception in the loop (an
unreadable frame, a full disk, a bug) ends it the same way, kept in `error`, so the caller can
save what was done and say how the run ended (the `kintinuous` command does:
docs/reliability.md).

The moving volume (config.volume.moving, on by default as in Kintinuous) works on the backend's
volume seen as a reference TsdfVolume (`backend.volume_view`), whose cyclical buffer
(tsdf.TsdfVolume.offset) it shifts.
"""

from __future__ import annotations

import time
import traceback
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from kintinuous_ref.backend import Backend, DeviceTraffic, ReferenceBackend
from kintinuous_ref.camera import Intrinsics
from kintinuous_ref.config import Config
from kintinuous_ref.datasets.tum import Frame, Trajectory
from kintinuous_ref.errors import ConfigError, KintinuousError
from kintinuous_ref.loop_closure.closer import LoopCloser
from kintinuous_ref.moving_volume import MovingVolume, SliceStore
from kintinuous_ref.plausibility import check_iterations
from kintinuous_ref.raycast import ModelPrediction
from kintinuous_ref.tsdf import TsdfVolume
from kintinuous_ref.vocabulary import GROUNDTRUTH, ODOMETRY_CHOICES

STAGES = ("preprocess", "odometry", "shift", "integrate", "raycast", "total")


@dataclass
class PipelineResult:
    timestamps: list[float] = field(default_factory=list)
    poses: list[np.ndarray] = field(default_factory=list)  # camera-to-world, one per frame
    fused: list[bool] = field(default_factory=list)  # False where tracking failed
    timings_ms: dict[str, list[float]] = field(default_factory=lambda: {s: [] for s in STAGES})
    # per stage and frame, what the host asked of the device (zeros without one)
    traffic: dict[str, list[DeviceTraffic]] = field(default_factory=lambda: {s: [] for s in STAGES})
    tracking_failures: int = 0
    failure_reasons: list[str] = field(default_factory=list)  # "frame i: reason"
    volume: TsdfVolume | None = None
    model: ModelPrediction | None = None  # the last prediction, if any (maps where computed)
    interrupted: bool = False
    moving: MovingVolume | None = None  # the cyclical buffer's state (None: a fixed volume)
    # the backend's volume -> a host TsdfVolume for meshing (Backend.host_volume)
    host_volume: Callable[[Any], TsdfVolume] | None = None
    # the backend's marching cubes (Backend.mesh), for the final mesh as for the slices
    contour: Callable[..., tuple[np.ndarray, np.ndarray]] | None = None
    volume_origins: list[np.ndarray] = field(default_factory=list)  # per frame, after its shift
    reason: str = ""  # why the run ended early (the signal, the error); "" when it completed
    error: Exception | None = None  # the exception that ended the loop (capture_errors)
    error_traceback: str = ""
    last_frame: int | None = None  # index of the last frame done
    signal_name: str = ""  # the signal that interrupted the run (SIGINT, SIGTERM, SIGHUP)
    loop_closer: LoopCloser | None = None  # keyframes, loops and corrections, when closing loops

    @property
    def status(self) -> str:
        """How the run ended: "completed", "interrupted" (a signal) or "failed" (an error)."""
        if self.interrupted:
            return "interrupted"
        return "failed" if self.error is not None else "completed"

    @property
    def shifts(self) -> int:
        return 0 if self.moving is None else self.moving.shifts

    @property
    def slices(self) -> int:
        return 0 if self.moving is None else self.moving.slices

    @property
    def frames(self) -> int:
        return len(self.poses)

    @property
    def trajectory(self) -> Trajectory:
        """The poses, corrected by every loop closed (all of them, also those of frames before
        the last closure), when loops were closed."""
        if self.loop_closer is not None and self.loop_closer.closures:
            return Trajectory(np.array(self.timestamps), self.loop_closer.corrected_poses())
        return Trajectory(np.array(self.timestamps), np.array(self.poses).reshape(-1, 4, 4))

    def timing_summary(self) -> dict[str, dict[str, float | None]]:
        """{stage: {mean, median, max}} in milliseconds; None for a stage that never ran."""
        summary: dict[str, dict[str, float | None]] = {}
        for stage, values in self.timings_ms.items():
            if values:
                summary[stage] = {
                    "mean": float(np.mean(values)),
                    "median": float(np.median(values)),
                    "max": float(np.max(values)),
                }
            else:
                summary[stage] = {"mean": None, "median": None, "max": None}
        return summary


def check_settings(
    config: Config, odometry: str, backend: Backend | None = None, loop_closure: bool = False
) -> None:
    """Refuse, before any data is read, settings a run cannot succeed with (one-line
    ConfigError): a config value, a volume too big for the memory of the backend that will hold
    it (`backend.tsdf.check_volume_config`), an unknown odometry, iterations that leave its
    tracker no work (`plausibility.check_iterations`), loop closure on a fixed volume.
    The one place these are checked; `check_run` adds what needs the dataset."""
    config.validate()
    (backend or ReferenceBackend()).tsdf.check_volume_config(config.volume)
    if odometry not in ODOMETRY_CHOICES:
        raise ConfigError(
            f"unknown odometry {odometry!r}; choose one of {', '.join(ODOMETRY_CHOICES)}"
        )
    check_iterations(config, odometry)
    if loop_closure and not config.volume.moving:
        raise ConfigError(
            "loop closure needs the moving volume (volume.moving = true): drop --fixed-volume"
        )


def check_groundtruth(odometry: str, groundtruth: Trajectory | None, dataset: str = "") -> None:
    """Refuse ground-truth odometry on a dataset without ground truth (`dataset`: its name for
    the message)."""
    if odometry == GROUNDTRUTH and groundtruth is None:
        where = f"{dataset}: " if dataset else ""
        raise ConfigError(
            f"{where}no ground-truth poses (groundtruth.txt, or --groundtruth for a log or bag), "
            "so --odometry groundtruth cannot run"
        )


def check_run(
    config: Config,
    odometry: str,
    groundtruth: Trajectory | None,
    backend: Backend | None = None,
    loop_closure: bool = False,
    dataset: str = "",
) -> None:
    """Refuse, before any work, a run that cannot succeed (one-line ConfigError): its settings
    (`check_settings`) and its dataset (`check_groundtruth`)."""
    check_settings(config, odometry, backend, loop_closure)
    check_groundtruth(odometry, groundtruth, dataset)


def run(
    frames: Iterable[Frame],
    camera: Intrinsics,
    config: Config,
    odometry: str = GROUNDTRUTH,
    groundtruth: Trajectory | None = None,
    backend: Backend | None = None,
    progress: Callable[[PipelineResult], None] | None = None,
    predict_model: bool | None = None,
    slices: Path | None = None,
    capture_errors: bool = False,
    loop_closer: LoopCloser | None = None,
    synchronize_stages: bool = False,
) -> PipelineResult:
    """Reconstruct a sequence. `groundtruth` holds one pose per frame INDEX of the sequence
    (TumSequence.groundtruth_for_frames()). `predict_model` None: raycast only when a tracker
    needs the model (ground-truth odometry does not). `progress` is called after every frame.
    `slices`: folder for the moving volume's slices (written as they leave); None keeps them in
    memory. `capture_errors`: an exception while reading or processing a frame ends the loop and
    is kept in the result's `error` (the work before it stays) instead of propagating.
    `backend` None: the reference. `loop_closer`: close loops (step 2b), which needs the moving
    volume. `synchronize_stages`: each stage's time waits for its device work
    (Backend.synchronize); otherwise an accelerator's work runs on while the host goes on, and
    a stage's time is the host's (the frame's total stays right over many frames)."""
    backend = backend or ReferenceBackend()
    check_run(config, odometry, groundtruth, backend, loop_closure=loop_closer is not None)
    if predict_model is None:
        predict_model = odometry != GROUNDTRUTH
    tracker = None
    if odometry != GROUNDTRUTH:
        tracker = backend.odometry.make_tracker(odometry, config, camera)
    stride = getattr(tracker, "model_stride", 1)  # only the pixels the tracker reads
    result = PipelineResult(loop_closer=loop_closer)
    if loop_closer is not None:
        result.timings_ms["loop_closure"] = []
        result.traffic["loop_closure"] = []
    previous = tracked_pose = None  # the last frame, and its pose in the volume's coordinates
    try:
        for frame in frames:
            clock = _Clock(
                backend.device_traffic, backend.synchronize if synchronize_stages else None
            )
            # 1. Preprocess (IV-A.1), where the backend computes.
            current = backend.preprocess.preprocess_frame(
                backend.upload(frame.colour), backend.upload(frame.depth), camera, config.preprocess
            )
            clock.lap("preprocess")
            # 2. Odometry (IV, V): where is this camera?
            ok, reason = True, ""
            if odometry == GROUNDTRUTH:
                pose = groundtruth.poses[frame.index]
            elif previous is None:
                pose = groundtruth.poses[frame.index] if groundtruth is not None else np.eye(4)
            else:
                tracked = tracker.track(previous, current, result.model, tracked_pose)
                pose, ok, reason = tracked.pose, tracked.ok, tracked.reason
            clock.lap("odometry")
            if result.volume is None:
                result.volume = backend.tsdf.make_volume(
                    config.volume, pose, config.colour.max_weight
                )
                if config.volume.moving:
                    result.moving = MovingVolume(
                        backend.volume_view(result.volume),
                        pose,
                        config.volume,
                        SliceStore(slices),
                        mesh_box=backend.mesh.mesh_box,
                    )
                result.host_volume = backend.host_volume
                result.contour = backend.mesh.marching_cubes
            # 2b. Loop closure: a closed loop moves the map's coordinates (closer.py).
            if loop_closer is not None:
                correction = loop_closer.observe(
                    frame.index, loop_closer.in_map(pose), current, frame.colour, frame.depth,
                    fused=ok,
                )  # fmt: skip
                if correction is not None and config.loop_closure.recentre_on_closure:
                    pose = correction @ pose
                    result.moving.recentre(pose)
                clock.lap("loop_closure")
            # 3. Moving volume (III, Fig. 2): shift, extracting the slices that leave.
            if ok and result.moving is not None:
                result.moving.update(pose)
            if loop_closer is not None:
                loop_closer.slice_made(frame.index, result.moving.slices)
            clock.lap("shift")
            # 4. Integrate depth and colour (III, VI); a frame whose tracking failed is not fused.
            if ok:
                backend.tsdf.integrate(
                    result.volume,
                    current.depth,
                    pose,
                    camera,
                    current.colour,
                    backend.colour.colour_weights(current, config.colour),
                )
            else:
                result.tracking_failures += 1
                result.failure_reasons.append(f"frame {frame.index}: {reason}")
            clock.lap("integrate")
            # 5. Predict the model surface for the next frame's ICP (III).
            if predict_model:
                result.model = backend.predict_surface(result.volume, pose, camera, stride=stride)
                clock.lap("raycast")
            # 6. Record.
            clock.total()
            for stage, milliseconds in clock.laps.items():
                result.timings_ms[stage].append(milliseconds)
                result.traffic[stage].append(clock.traffic[stage])
            result.timestamps.append(frame.timestamp)
            tracked_pose = np.asarray(pose, dtype=np.float64)
            result.poses.append(tracked_pose if loop_closer is None else loop_closer.in_map(pose))
            result.fused.append(ok)
            result.volume_origins.append(np.array(result.volume.origin, dtype=np.float64))
            result.last_frame = frame.index
            previous = current
            if progress is not None:
                progress(result)
    except KeyboardInterrupt as stop:
        result.interrupted = True
        result.signal_name = getattr(stop, "signal_name", "SIGINT")
        result.reason = f"interrupted by {result.signal_name}"
    except Exception as err:
        if not capture_errors:
            raise
        result.error, result.error_traceback = err, traceback.format_exc()
        result.reason = error_reason(err)
    if loop_closer is not None:  # the closer may have seen a frame that ended before its record
        loop_closer.keep_frames(result.frames)
    return result


def error_reason(err: Exception) -> str:
    """One line for an exception that ended a run: the message of a project error, the file
    and cause of an OSError, and for anything else that it is a bug."""
    if isinstance(err, KintinuousError):
        return str(err)
    if isinstance(err, OSError):
        where = f"{err.filename}: " if err.filename else ""
        return f"cannot write: {where}{err.strerror or err}"
    if isinstance(err, MemoryError):
        return "out of memory"
    return f"internal error (a bug, please report it): {type(err).__name__}: {err}"


class _Clock:
    """Milliseconds and device traffic (DeviceTraffic) per stage of one frame."""

    def __init__(
        self, traffic: Callable[[], DeviceTraffic], wait: Callable[[], None] | None = None
    ) -> None:
        self.count = traffic
        self.wait = wait  # called before each lap: the device's work joins its stage
        self.start = self.last = time.perf_counter()
        self.first = self.counted = traffic()
        self.laps: dict[str, float] = {}
        self.traffic: dict[str, DeviceTraffic] = {}

    def lap(self, stage: str) -> None:
        if self.wait is not None:
            self.wait()
        now, counted = time.perf_counter(), self.count()
        self.laps[stage] = 1000.0 * (now - self.last)
        self.traffic[stage] = counted - self.counted
        self.last, self.counted = now, counted

    def total(self) -> None:
        self.laps["total"] = 1000.0 * (time.perf_counter() - self.start)
        self.traffic["total"] = self.count() - self.first
