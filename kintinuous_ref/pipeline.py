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

The backend is a parameter: any object whose `preprocess`, `tsdf` and `raycast` attributes offer
kintinuous_ref's functions of those modules (kintinuous_ref itself, or a kintinuous_fast backend,
whose `odometry.make_tracker` then tracks, whose `colour` computes the colour weights, whose
`tsdf.slab_view` lets the moving volume work on its volume and whose `tsdf.to_reference_volume`
hands the final volume to meshing). State stays where the backend computes: a fast backend's
`upload` puts each frame's two images there once and its `predict_surface` leaves the raycast
maps there, so with cuda the frames, maps and volume live in GPU memory for the whole run and
only poses, the trackers' 6x6 systems and the outputs cross to the host.

Volume placement and the tracker's start need the first pose: with ground-truth odometry it is
the ground truth; with a tracker it is the first ground-truth pose when the dataset has one (so
trajectories are comparable with it), else the identity.

Ctrl-C (KeyboardInterrupt), and SIGTERM or SIGHUP once `handle_signals` is in force (the command
line's), end the loop cleanly: the result holds the poses so far and the volume of what was
fused, with `interrupted` and `reason` set. With `capture_errors` an exception in the loop (an
unreadable frame, a full disk, a bug) ends it the same way, kept in `error`. `reconstruct` then
saves what was done (every file written under a temporary name and renamed into place) and says
how the run ended in report.json's "status": "completed", "interrupted" or "failed".

The moving volume (config.volume.moving, on by default as in Kintinuous) needs the reference
volume's cyclical buffer (tsdf.TsdfVolume.offset); with a backend whose volume has none the
volume stays fixed, and `moving_volume_note` says so.
"""

from __future__ import annotations

import contextlib
import functools
import os
import shutil
import sys
import time
import traceback
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np

import kintinuous_ref
import kintinuous_ref.colour
import kintinuous_ref.preprocess
import kintinuous_ref.raycast
import kintinuous_ref.tsdf
from kintinuous_ref.camera import Intrinsics
from kintinuous_ref.config import Config
from kintinuous_ref.datasets.tum import Frame, FrameSequence, Trajectory
from kintinuous_ref.errors import ConfigError, DatasetError, InternalError, KintinuousError
from kintinuous_ref.moving_volume import MovingVolume, SliceStore
from kintinuous_ref.raycast import ModelPrediction
from kintinuous_ref.signals import Interrupted
from kintinuous_ref.strict_json import dumps as strict_dumps
from kintinuous_ref.tsdf import TsdfVolume

GROUNDTRUTH = "groundtruth"
STAGES = ("preprocess", "odometry", "shift", "integrate", "raycast", "total")


@dataclass
class PipelineResult:
    timestamps: list[float] = field(default_factory=list)
    poses: list[np.ndarray] = field(default_factory=list)  # camera-to-world, one per frame
    fused: list[bool] = field(default_factory=list)  # False where tracking failed
    timings_ms: dict[str, list[float]] = field(default_factory=lambda: {s: [] for s in STAGES})
    tracking_failures: int = 0
    failure_reasons: list[str] = field(default_factory=list)  # "frame i: reason"
    volume: TsdfVolume | None = None
    model: ModelPrediction | None = None  # the last prediction, if any (maps where computed)
    interrupted: bool = False
    moving: MovingVolume | None = None  # the cyclical buffer's state (None: a fixed volume)
    moving_volume_note: str = ""  # why the volume stayed fixed although config asked to move
    # the backend's volume -> a host TsdfVolume (fast backends' to_reference_volume); None: as is
    host_volume: Callable[[Any], TsdfVolume] | None = None
    volume_origins: list[np.ndarray] = field(default_factory=list)  # per frame, after its shift
    reason: str = ""  # why the run ended early (the signal, the error); "" when it completed
    error: Exception | None = None  # the exception that ended the loop (capture_errors)
    error_traceback: str = ""
    last_frame: int | None = None  # index of the last frame done
    signal_name: str = ""  # the signal that interrupted the run (SIGINT, SIGTERM, SIGHUP)

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


def check_run(
    config: Config,
    odometry: str,
    groundtruth: Trajectory | None,
    backend: ModuleType | Any = kintinuous_ref,
) -> None:
    """Refuse, before any work, a run that cannot succeed (one-line KintinuousError). The volume
    is checked against the memory of the backend that will hold it (`backend.tsdf`)."""
    config.validate()
    backend.tsdf.check_volume_config(config.volume)
    if odometry == GROUNDTRUTH and groundtruth is None:
        raise ConfigError("--odometry groundtruth needs a dataset with ground-truth poses")
    if odometry != GROUNDTRUTH:
        from kintinuous_ref.odometry import METHODS

        if odometry not in METHODS:
            choices = ", ".join((GROUNDTRUTH, *METHODS))
            raise ConfigError(f"unknown odometry {odometry!r}; choose one of {choices}")


def run(
    frames: Iterable[Frame],
    camera: Intrinsics,
    config: Config,
    odometry: str = GROUNDTRUTH,
    groundtruth: Trajectory | None = None,
    backend: ModuleType | Any = kintinuous_ref,
    progress: Callable[[PipelineResult], None] | None = None,
    predict_model: bool | None = None,
    slices: Path | None = None,
    capture_errors: bool = False,
) -> PipelineResult:
    """Reconstruct a sequence. `groundtruth` holds one pose per frame INDEX of the sequence
    (TumSequence.groundtruth_for_frames()). `predict_model` None: raycast only when a tracker
    needs the model (ground-truth odometry does not). `progress` is called after every frame.
    `slices`: folder for the moving volume's slices (written as they leave); None keeps them in
    memory. `capture_errors`: an exception while reading or processing a frame ends the loop and
    is kept in the result's `error` (the work before it stays) instead of propagating."""
    check_run(config, odometry, groundtruth, backend)
    if predict_model is None:
        predict_model = odometry != GROUNDTRUTH
    tracker = None
    if odometry != GROUNDTRUTH:
        # The backend's tracker (kintinuous_fast's dense systems), else the reference's.
        make_tracker = getattr(getattr(backend, "odometry", None), "make_tracker", None)
        if make_tracker is None:
            from kintinuous_ref.odometry import make_tracker
        tracker = make_tracker(odometry, config, camera)
    # Where the backend keeps its arrays (device memory for cuda); the reference's defaults.
    upload = getattr(backend, "upload", _as_given)
    colour = getattr(backend, "colour", kintinuous_ref.colour)
    predict_surface = getattr(
        backend, "predict_surface", functools.partial(backend.raycast.raycast, colour=False)
    )
    stride = getattr(tracker, "model_stride", 1)  # only the pixels the tracker reads
    result = PipelineResult()
    previous = None
    try:
        for frame in frames:
            clock = _Clock()
            # 1. Preprocess (IV-A.1), where the backend computes.
            current = backend.preprocess.preprocess_frame(
                upload(frame.colour), upload(frame.depth), camera, config.preprocess
            )
            clock.lap("preprocess")
            # 2. Odometry (IV, V): where is this camera?
            ok, reason = True, ""
            if odometry == GROUNDTRUTH:
                pose = groundtruth.poses[frame.index]
            elif previous is None:
                pose = groundtruth.poses[frame.index] if groundtruth is not None else np.eye(4)
            else:
                tracked = tracker.track(previous, current, result.model, result.poses[-1])
                pose, ok, reason = tracked.pose, tracked.ok, tracked.reason
            clock.lap("odometry")
            if result.volume is None:
                result.volume = backend.tsdf.make_volume(
                    config.volume, pose, config.colour.max_weight
                )
                result.moving, result.moving_volume_note = _moving_volume(
                    result.volume, pose, config, slices, getattr(backend.tsdf, "slab_view", None)
                )
                result.host_volume = getattr(backend.tsdf, "to_reference_volume", None)
            # 3. Moving volume (III, Fig. 2): shift, extracting the slices that leave.
            if ok and result.moving is not None:
                result.moving.update(pose)
            clock.lap("shift")
            # 4. Integrate depth and colour (III, VI); a frame whose tracking failed is not fused.
            if ok:
                backend.tsdf.integrate(
                    result.volume,
                    current.depth,
                    pose,
                    camera,
                    current.colour,
                    colour.colour_weights(current, config.colour),
                )
            else:
                result.tracking_failures += 1
                result.failure_reasons.append(f"frame {frame.index}: {reason}")
            clock.lap("integrate")
            # 5. Predict the model surface for the next frame's ICP (III).
            if predict_model:
                result.model = predict_surface(result.volume, pose, camera, stride=stride)
                clock.lap("raycast")
            # 6. Record.
            clock.total()
            for stage, milliseconds in clock.laps.items():
                result.timings_ms[stage].append(milliseconds)
            result.timestamps.append(frame.timestamp)
            result.poses.append(np.asarray(pose, dtype=np.float64))
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
        result.reason = _error_reason(err)
    return result


def _error_reason(err: Exception) -> str:
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


def _as_given(array: Any) -> Any:
    """The reference computes on the host: frames stay as read."""
    return array


def _moving_volume(
    volume: Any,
    first_pose: np.ndarray,
    config: Config,
    slices: Path | None,
    view: Callable[[Any], Any] | None = None,
) -> tuple[MovingVolume | None, str]:
    """The cyclical buffer around a new volume, or None with the reason it stays fixed. `view`
    (a fast backend's tsdf.slab_view) shows another backend's volume as a TsdfVolume."""
    if not config.volume.moving:
        return None, ""
    if not isinstance(volume, TsdfVolume) and view is not None:
        volume = view(volume)
    elif not isinstance(volume, TsdfVolume):
        return None, f"fixed volume: the {type(volume).__name__} backend has no cyclical buffer"
    return MovingVolume(volume, first_pose, config.volume, SliceStore(slices)), ""


class _Clock:
    """Milliseconds per stage of one frame."""

    def __init__(self) -> None:
        self.start = self.last = time.perf_counter()
        self.laps: dict[str, float] = {}

    def lap(self, stage: str) -> None:
        now = time.perf_counter()
        self.laps[stage] = 1000.0 * (now - self.last)
        self.last = now

    def total(self) -> None:
        self.laps["total"] = 1000.0 * (time.perf_counter() - self.start)


# ----------------------------------------------------------------------------------------------
# `kintinuous reconstruct`: a dataset in, a folder of results out.

DEFAULT_DATASET = "desk"
SCENARIO_FRAMES = 300  # length of a built-in scenario generated into the cache


def cache_folder() -> Path:
    """Where generated scenarios are kept: $KINTINUOUS_CACHE, else ~/.cache/kintinuous."""
    root = os.environ.get("KINTINUOUS_CACHE")
    return Path(root) if root else Path.home() / ".cache" / "kintinuous"


def open_dataset(
    dataset: str | None,
    intrinsics: str | None = None,
    progress: bool = False,
    *,
    size: tuple[int, int] | None = None,
    groundtruth: Path | None = None,
    topics: str | None = None,
    need_camera: bool = True,
    frames_needed: int | None = None,
) -> FrameSequence:
    """Any input the system reads (docs/datasets.md), `desk` when `dataset` is None:

    - a `.klg` log (Kintinuous / ElasticFusion): `size` (default 640x480) and `intrinsics`
      (fx,fy,cx,cy or a JSON file) say what the log does not; without a camera (only when
      `need_camera` is False, for conversion) frames can still be read;
    - a ROS1 `.bag` or ROS2 bag folder: topics `rgb,depth,info` (default TUM's, then
      RealSense's), camera from its CameraInfo unless `intrinsics` is given;
    - a TUM RGB-D folder;
    - a sequence fetched with `kintinuous download` (fr1/desk, ...), from the cache;
    - a built-in synthetic scenario by name (rendered into the cache on first use, its first
      `frames_needed` frames only when that is given).

    `groundtruth` (a TUM trajectory file) gives a log or a bag its ground truth.
    """
    from kintinuous_ref.camera import intrinsics_from_option
    from kintinuous_ref.datasets import bag, download, klg, synthetic, tum

    dataset = dataset or DEFAULT_DATASET
    path = Path(dataset)
    width, height = size or klg.DEFAULT_SIZE
    camera = intrinsics_from_option(intrinsics, width, height) if intrinsics else None
    if path.suffix == ".klg":
        if camera is None and need_camera:
            raise ConfigError(
                f"{path}: a .klg log holds no camera: pass --intrinsics fx,fy,cx,cy "
                "(and --size WxH unless 640x480)"
            )
        if camera is not None and size is None:  # a JSON camera gives the size
            width, height = camera.width, camera.height
        return klg.open_log(path, (width, height), camera, groundtruth)
    if size is not None and intrinsics is None:
        raise ConfigError("--size is the image size of a .klg log, or of --intrinsics fx,fy,cx,cy")
    if bag.is_bag(path):
        chosen = bag.parse_topics(topics) if topics else None
        return bag.open_bag(path, chosen, camera, groundtruth)
    for option, value in (("--groundtruth", groundtruth), ("--topics", topics)):
        if value is not None:
            raise ConfigError(f"{option} applies to .klg logs and bags, not to {dataset}")
    if path.is_dir():
        return tum.open_sequence(path, intrinsics)
    downloaded = download.cached(dataset, cache_folder() / "tum")
    if downloaded is not None:
        return tum.open_sequence(downloaded, intrinsics)
    if dataset in download.SEQUENCES:
        raise DatasetError(
            f"{dataset}: not downloaded yet: run `kintinuous download {dataset}` first"
        )
    scenarios = synthetic.list_scenarios()
    if dataset not in scenarios:
        raise DatasetError(
            f"{dataset}: neither a dataset folder nor a scenario ({', '.join(scenarios)}), "
            "nor a .klg log, a bag or a downloaded sequence"
        )
    folder = cache_folder() / dataset
    # A scenario is rendered only as far as a run needs it (`frames_needed`, all by default),
    # and extended when a later run needs more.
    needed = (
        SCENARIO_FRAMES if frames_needed is None else min(max(frames_needed, 1), SCENARIO_FRAMES)
    )
    if rendered_frames(folder) < needed:
        synthetic.write_scenario(
            dataset, folder, frames=SCENARIO_FRAMES, progress=progress, render=needed
        )
    return tum.open_sequence(folder, intrinsics)


def rendered_frames(folder: Path) -> int:
    """Frames a scenario folder in the cache holds (its associations.txt is written last)."""
    listing = folder / "associations.txt"
    if not listing.is_file():
        return 0
    return sum(1 for line in listing.read_text().splitlines() if line and line[0] != "#")


# Beyond this many triangles the preview shows a coarser mesh (moving_volume.preview_mesh): its
# render then costs the same memory however long the run.
PREVIEW_TRIANGLES = 200_000


# What a run writes into its folder: a folder holding any of these holds an earlier result.
RESULT_NAMES = (
    "report.json",
    "trajectory.txt",
    "mesh.ply",
    "slices",
    "preview.png",
    "volume_origins.txt",
    "crash.log",
)


def check_output(out: str | Path, overwrite: bool = False) -> Path:
    """The output folder `out`, refused (ConfigError) when empty, a file, or holding an earlier
    result without `overwrite`. Changes nothing on disk."""
    if not str(out).strip():
        raise ConfigError("--out is empty: name an output folder")
    path = Path(out)
    if path.exists() and not path.is_dir():
        raise ConfigError(f"{path}: exists and is not a folder; --out names a folder")
    if path.is_dir() and not overwrite:
        earlier = [name for name in RESULT_NAMES if (path / name).exists()]
        if earlier:
            raise ConfigError(
                f"{path}: holds an earlier result ({', '.join(earlier)}); pass --overwrite to "
                "replace it, or choose another --out"
            )
    return path


def prepare_output(out: str | Path, overwrite: bool = False) -> Path:
    """`check_output`, then the earlier result removed (with `overwrite`) and the folder made
    and shown to be writable, before a run starts: a run never mixes with an older one."""
    path = check_output(out, overwrite)
    try:
        if path.is_dir():
            for name in RESULT_NAMES:
                old = path / name
                if old.is_dir() and not old.is_symlink():
                    shutil.rmtree(old)
                elif old.exists() or old.is_symlink():
                    old.unlink()
        path.mkdir(parents=True, exist_ok=True)
        with _atomic(path / ".write-test"):
            pass
        (path / ".write-test").unlink()
    except OSError as err:
        raise ConfigError(
            f"{path}: cannot write the output folder ({err.strerror or err})"
        ) from None
    return path


@contextlib.contextmanager
def _atomic(path: Path) -> Iterator[Path]:
    """A temporary name beside `path` (same suffix) to write to; renamed to `path` when the
    block ends, removed when it raises: no reader ever sees half a file."""
    temporary = path.with_name(f".{path.stem}.partial{path.suffix}")
    try:
        yield temporary
        if not temporary.exists():  # the writer wrote nothing (an empty block)
            temporary.touch()
        os.replace(temporary, path)
    except BaseException:
        with contextlib.suppress(OSError):
            temporary.unlink()
        raise


def write_text_atomic(path: Path, text: str) -> None:
    """`text` into `path`, written under a temporary name and renamed."""
    with _atomic(Path(path)) as temporary:
        temporary.write_text(text)


def write_outputs(
    result: PipelineResult,
    out: Path,
    report: dict[str, Any],
    preview: bool = True,
    saved: list[str] | None = None,
) -> dict[str, Any]:
    """trajectory.txt, mesh.ply, volume_origins.txt, preview.png and report.json in `out`;
    returns the report. Each file is written atomically, in that order, and its name appended to
    `saved` once in place. A file that cannot be written (a full disk, a failed render) is left
    out and named in the report's "not_saved" with the reason; report.json itself must be
    written (its OSError propagates)."""
    from kintinuous_ref import mesh as meshing
    from kintinuous_ref.datasets.tum import write_trajectory

    saved = [] if saved is None else saved
    not_saved: dict[str, str] = {}
    out.mkdir(parents=True, exist_ok=True)

    def attempt(name: str, write: Callable[[Path], Any]) -> Any:
        try:
            with _atomic(out / name) as temporary:
                value = write(temporary)
        except Exception as err:  # kept in the report; the next file is still tried
            not_saved[name] = _error_reason(err)
            return None
        saved.append(name)
        return value

    attempt("trajectory.txt", lambda path: write_trajectory(path, result.trajectory))
    surface, mesh_size = None, None
    if result.moving is not None and result.volume is not None:
        # The rest of the window is the last slice; the slices merge into one mesh on disk.
        from kintinuous_ref import moving_volume

        try:
            result.moving.finish()
        except Exception as err:  # the last slice is missing, so the mesh would be too
            not_saved["slices"] = not_saved["mesh.ply"] = _error_reason(err)
        else:
            mesh_size = attempt(
                "mesh.ply", lambda path: moving_volume.assemble(result.moving.store, path)
            )
        # The window at each frame (after its shift): timestamp, voxel (0, 0, 0)'s centre.
        rows = np.column_stack([result.timestamps, np.reshape(result.volume_origins, (-1, 3))])
        attempt(
            "volume_origins.txt",
            lambda path: np.savetxt(path, rows, fmt="%.6f", header="timestamp x y z"),
        )
        if preview and mesh_size is not None:  # the mesh grows with the path; its preview does not
            try:
                surface = moving_volume.preview_mesh(
                    result.moving.store, result.volume.voxel_size, PREVIEW_TRIANGLES, mesh_size[1]
                )
            except Exception as err:
                not_saved["preview.png"] = _error_reason(err)
    elif result.volume is not None:
        volume = result.volume
        try:
            if result.host_volume is not None:  # a fast backend's volume, as a host TsdfVolume
                volume = result.host_volume(volume)
            surface = meshing.extract_mesh(volume)
        except Exception as err:
            not_saved["mesh.ply"] = _error_reason(err)
        if surface is not None:
            attempt("mesh.ply", lambda path: meshing.write_ply(path, surface))
            if "mesh.ply" in saved:
                mesh_size = (len(surface.points), len(surface.triangles))
    if preview and surface is not None:
        first = result.poses[0] if result.poses else None
        attempt("preview.png", lambda path: meshing.render_preview(surface, path, view_pose=first))
    report = {
        **report,
        "status": result.status,
        "reason": result.reason or None,
        "last_frame": result.last_frame,
        "frames": result.frames,
        "fused_frames": int(np.sum(result.fused)),
        "tracking_failures": result.tracking_failures,
        "failure_reasons": result.failure_reasons[:50],
        "interrupted": result.interrupted,
        "timing_ms": result.timing_summary(),
        "mesh": {
            "vertices": None if mesh_size is None else int(mesh_size[0]),
            "triangles": None if mesh_size is None else int(mesh_size[1]),
        },
        "moving_volume": result.moving is not None,
        "shifts": result.shifts,
        "slices": result.slices,
        "saved": [*saved, "report.json"],
        "not_saved": not_saved,
    }
    if result.moving_volume_note:
        report["moving_volume_note"] = result.moving_volume_note
    if result.volume is not None:
        report["volume"] = {
            "resolution": result.volume.resolution,
            "size_m": result.volume.size,
            "voxel_m": result.volume.voxel_size,
            "truncation_m": result.volume.truncation,
            "origin": result.volume.origin.tolist(),
        }
    write_text_atomic(out / "report.json", strict_dumps(report, indent=2) + "\n")
    saved.append("report.json")
    return report


def _bad_frames_checked(
    sequence: FrameSequence, start: int, count: int, skip: bool, skipped: list[str]
) -> Iterator[Frame]:
    """The frames start.. of a sequence; an unreadable one (corrupt, wrong size) is a
    DatasetError naming the frame and its file, or with `skip` left out and listed in
    `skipped`."""
    for index in range(start, start + count):
        try:
            frame = sequence[index]
        except DatasetError as err:
            message = f"frame {index}: {err}"
            if not skip:
                raise DatasetError(message) from None
            skipped.append(message)
            continue
        yield frame


def reconstruct(
    sequence: FrameSequence,
    out: Path,
    config: Config,
    odometry: str = GROUNDTRUTH,
    start: int = 0,
    count: int | None = None,
    backend_name: str = "ref",
    show_progress: bool = True,
    predict_model: bool | None = None,
    overwrite: bool = False,
    skip_bad_frames: bool = False,
) -> dict[str, Any]:
    """Run the pipeline over frames start.. of a sequence and write the outputs into `out`.

    Everything that can be checked is checked before the first frame is read; `out` must not
    hold an earlier result unless `overwrite` (which removes it first). However the run ends,
    what was done is saved (write_outputs) with its status; then an interrupted run raises
    Interrupted, a failed one a one-line KintinuousError (InternalError for a bug, whose
    traceback goes to crash.log in `out`). An unreadable frame ends the run, or with
    `skip_bad_frames` is left out and counted in the report's "skipped_frames".
    """
    from kintinuous_fast import select_backend

    backend = select_backend(backend_name)  # ConfigError when it cannot run here
    if not 0 <= start < len(sequence):
        raise ConfigError(f"--start {start} outside the sequence's frames 0..{len(sequence) - 1}")
    if count is not None and count <= 0:
        raise ConfigError(f"--frames must be positive, got {count}")
    groundtruth = None
    if sequence.groundtruth is not None:
        try:
            groundtruth = sequence.groundtruth_for_frames()
        except DatasetError:
            if odometry == GROUNDTRUTH:
                raise
    if odometry == GROUNDTRUTH and groundtruth is None:
        raise ConfigError(
            f"{sequence.path}: no ground truth (groundtruth.txt, or --groundtruth for a log or "
            "bag), so --odometry groundtruth cannot run"
        )
    check_run(config, odometry, groundtruth, backend)
    out = prepare_output(out, overwrite)
    total = (len(sequence) - start) if count is None else min(count, len(sequence) - start)
    bar = None
    if show_progress:
        from tqdm import tqdm

        bar = tqdm(total=total, unit="frame", desc="reconstruct")
    skipped: list[str] = []
    try:
        result = run(
            _bad_frames_checked(sequence, start, total, skip_bad_frames, skipped),
            sequence.camera,
            config,
            odometry,
            groundtruth,
            progress=(lambda _: bar.update(1)) if bar is not None else None,
            predict_model=predict_model,
            slices=out / "slices",
            backend=backend,
            capture_errors=True,
        )
    except BaseException:
        if bar is not None:
            bar.close()
        raise
    info = {
        "dataset": str(sequence.path),
        "odometry": odometry,
        "backend": backend.name,
        "start": start,
        "skipped_frames": len(skipped),
        "skipped_reasons": skipped[:50],
    }
    saved: list[str] = []
    try:
        if bar is not None:
            bar.close()  # the one-line messages below start on a line of their own
        print(f"saving {result.frames} frames...", file=sys.stderr, flush=True)
        if result.error is not None and not isinstance(result.error, KintinuousError | OSError):
            write_text_atomic(out / "crash.log", result.error_traceback)
            saved.append("crash.log")
        report = write_outputs(result, out, info, saved=saved)
    except KeyboardInterrupt as again:
        name = getattr(again, "signal_name", "SIGINT")
        names = ["trajectory.txt", "mesh.ply", "preview.png", "report.json"]
        if result.moving is not None:
            names.insert(2, "volume_origins.txt")
        missing = [n for n in names if n not in saved]
        raise Interrupted(
            name,
            f"{name} during the save: saved {', '.join(saved) or 'nothing'} in {out}; NOT saved: "
            f"{', '.join(missing)}",
        ) from None
    except OSError as err:
        raise KintinuousError(
            f"{out}: cannot save the run ({_error_reason(err)}); saved: "
            f"{', '.join(saved) or 'nothing'}"
        ) from None
    kept = f"the {result.frames} frames done are saved in {out}"
    if report["not_saved"]:
        problems = "; ".join(f"{k}: {v}" for k, v in report["not_saved"].items())
        kept = f"saved {', '.join(report['saved'])} in {out} but NOT {problems}"
    if result.interrupted:
        raise Interrupted(
            result.signal_name,
            f"{result.reason} after frame {result.last_frame}: {kept}",
        )
    if result.error is not None:
        if "crash.log" in saved:
            raise InternalError(f"{result.reason}; traceback in {out / 'crash.log'}; {kept}")
        raise KintinuousError(f"{result.reason}; {kept}")
    if report["not_saved"]:
        raise KintinuousError(kept)
    return report
