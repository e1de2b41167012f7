"""The per-frame loop of the system as one "algorithm box" (paper III-V, design.md).

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

Ctrl-C (KeyboardInterrupt) ends the loop cleanly: the result holds the poses so far and the
volume of what was fused, with `interrupted` set. Slices already written to disk stay there even
if the run crashes.

The moving volume (config.volume.moving, on by default as in Kintinuous) needs the reference
volume's cyclical buffer (tsdf.TsdfVolume.offset); with a backend whose volume has none the
volume stays fixed, and `moving_volume_note` says so.
"""

from __future__ import annotations

import functools
import json
import os
import time
from collections.abc import Callable, Iterable
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
from kintinuous_ref.errors import ConfigError, DatasetError
from kintinuous_ref.moving_volume import MovingVolume, SliceStore
from kintinuous_ref.raycast import ModelPrediction
from kintinuous_ref.tsdf import TsdfVolume, check_volume_config

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


def check_run(config: Config, odometry: str, groundtruth: Trajectory | None) -> None:
    """Refuse, before any work, a run that cannot succeed (one-line KintinuousError)."""
    config.validate()
    check_volume_config(config.volume)
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
) -> PipelineResult:
    """Reconstruct a sequence. `groundtruth` holds one pose per frame INDEX of the sequence
    (TumSequence.groundtruth_for_frames()). `predict_model` None: raycast only when a tracker
    needs the model (ground-truth odometry does not). `progress` is called after every frame.
    `slices`: folder for the moving volume's slices (written as they leave); None keeps them in
    memory."""
    check_run(config, odometry, groundtruth)
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
            previous = current
            if progress is not None:
                progress(result)
    except KeyboardInterrupt:
        result.interrupted = True
    return result


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
) -> FrameSequence:
    """Any input the system reads (docs/datasets.md), `desk` when `dataset` is None:

    - a `.klg` log (Kintinuous / ElasticFusion): `size` (default 640x480) and `intrinsics`
      (fx,fy,cx,cy or a JSON file) say what the log does not; without a camera (only when
      `need_camera` is False, for conversion) frames can still be read;
    - a ROS1 `.bag` or ROS2 bag folder: topics `rgb,depth,info` (default TUM's, then
      RealSense's), camera from its CameraInfo unless `intrinsics` is given;
    - a TUM RGB-D folder;
    - a sequence fetched with `kintinuous download` (fr1/desk, ...), from the cache;
    - a built-in synthetic scenario by name (rendered into the cache on first use).

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
    if not (folder / "associations.txt").is_file():  # written last: a complete folder
        synthetic.write_scenario(dataset, folder, frames=SCENARIO_FRAMES, progress=progress)
    return tum.open_sequence(folder, intrinsics)


# Beyond this many triangles the preview shows a coarser mesh (moving_volume.preview_mesh): its
# render then costs the same memory however long the run.
PREVIEW_TRIANGLES = 200_000


def write_outputs(
    result: PipelineResult, out: Path, report: dict[str, Any], preview: bool = True
) -> dict[str, Any]:
    """mesh.ply, trajectory.txt, preview.png and report.json in `out`; returns the report."""
    from kintinuous_ref import mesh as meshing
    from kintinuous_ref.datasets.tum import write_trajectory

    out.mkdir(parents=True, exist_ok=True)
    write_trajectory(out / "trajectory.txt", result.trajectory)
    if result.moving is not None:
        # The rest of the window is the last slice; the slices merge into one mesh on disk.
        from kintinuous_ref import moving_volume

        result.moving.finish()
        mesh_size = moving_volume.assemble(result.moving.store, out / "mesh.ply")
        # The window at each frame (after its shift): timestamp, voxel (0, 0, 0)'s centre.
        rows = np.column_stack([result.timestamps, np.reshape(result.volume_origins, (-1, 3))])
        np.savetxt(out / "volume_origins.txt", rows, fmt="%.6f", header="timestamp x y z")
        if preview:  # the mesh grows with the path; its preview does not
            surface = moving_volume.preview_mesh(
                result.moving.store, result.volume.voxel_size, PREVIEW_TRIANGLES, mesh_size[1]
            )
    else:
        volume = result.volume
        if result.host_volume is not None:  # a fast backend's volume, as a host TsdfVolume
            volume = result.host_volume(volume)
        surface = meshing.extract_mesh(volume)
        meshing.write_ply(out / "mesh.ply", surface)
        mesh_size = (len(surface.points), len(surface.triangles))
    if preview:
        first = result.poses[0] if result.poses else None
        meshing.render_preview(surface, out / "preview.png", view_pose=first)
    report = {
        **report,
        "frames": result.frames,
        "fused_frames": int(np.sum(result.fused)),
        "tracking_failures": result.tracking_failures,
        "failure_reasons": result.failure_reasons[:50],
        "interrupted": result.interrupted,
        "timing_ms": result.timing_summary(),
        "mesh": {"vertices": mesh_size[0], "triangles": mesh_size[1]},
        "moving_volume": result.moving is not None,
        "shifts": result.shifts,
        "slices": result.slices,
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
    (out / "report.json").write_text(json.dumps(report, indent=2) + "\n")
    return report


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
) -> dict[str, Any]:
    """Run the pipeline over frames start.. of a sequence and write the outputs into `out`.

    Everything that can be checked is checked before the first frame is read. An interrupted run
    (Ctrl-C) still writes what it has and then re-raises KeyboardInterrupt.
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
    check_run(config, odometry, groundtruth)
    total = (len(sequence) - start) if count is None else min(count, len(sequence) - start)
    bar = None
    if show_progress:
        from tqdm import tqdm

        bar = tqdm(total=total, unit="frame", desc="reconstruct")
    try:
        result = run(
            sequence.frames(start, total),
            sequence.camera,
            config,
            odometry,
            groundtruth,
            progress=(lambda _: bar.update(1)) if bar is not None else None,
            predict_model=predict_model,
            slices=Path(out) / "slices",
            backend=backend,
        )
    finally:  # an unreadable frame's one-line error then starts on a line of its own
        if bar is not None:
            bar.close()
    report = write_outputs(
        result,
        Path(out),
        {
            "dataset": str(sequence.path),
            "odometry": odometry,
            "backend": backend.name,
            "start": start,
        },
    )
    if result.interrupted:
        raise KeyboardInterrupt
    return report
