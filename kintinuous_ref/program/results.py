"""A run's results on disk: the output folder checked and prepared before the run (never mixed
with an earlier run's), and what the run did written into it however it ended (trajectory,
mesh, volume origins, preview and report.json, each under a temporary name renamed into place).
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from kintinuous_ref.datasets.tum import Trajectory
from kintinuous_ref.errors import ConfigError
from kintinuous_ref.pipeline import PipelineResult, error_reason
from kintinuous_ref.plausibility import run_warnings
from kintinuous_ref.program.output_folder import (
    atomic,
    check_folder_path,
    refuse_earlier,
    remove,
    write_text_atomic,
)
from kintinuous_ref.strict_json import dumps as strict_dumps

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
    "trajectory_uncorrected.txt",
    "trajectory_loops.png",
)


def check_output(out: str | Path, overwrite: bool = False) -> Path:
    """The output folder `out`, refused (ConfigError) when empty, a file, or holding an earlier
    result without `overwrite`. An empty slices/ folder (or one holding only unfinished .part
    slices), which a killed run leaves, is no result: prepare_output removes it. Changes
    nothing on disk."""
    path = check_folder_path(out)
    if path.is_dir() and not overwrite:
        earlier = [name for name in RESULT_NAMES if _holds_result(path / name)]
        if earlier:
            raise refuse_earlier(path, earlier)
    return path


def _holds_result(path: Path) -> bool:
    """Whether `path`, one of RESULT_NAMES, is an earlier run's output."""
    if path.name == "slices" and path.is_dir() and not path.is_symlink():
        return any(not entry.name.endswith(".part") for entry in path.iterdir())
    return path.exists()


def prepare_output(out: str | Path, overwrite: bool = False) -> Path:
    """`check_output`, then the earlier result removed (with `overwrite`), a killed run's
    leftovers removed (an empty slices/, temporaries), and the folder made and shown to be
    writable, before a run starts: a run never mixes with an older one. Called under
    `locked(out)`, so that no live run owns what it removes."""
    path = check_output(out, overwrite)
    try:
        path.mkdir(parents=True, exist_ok=True)
        remove(path, RESULT_NAMES)  # without overwrite only leftovers remain among them
        with atomic(path / ".write-test"):
            pass
        (path / ".write-test").unlink()
    except OSError as err:
        raise ConfigError(
            f"{path}: cannot write the output folder ({err.strerror or err})"
        ) from None
    return path


def write_outputs(
    result: PipelineResult,
    out: Path,
    report: dict[str, Any],
    preview: bool = True,
    saved: list[str] | None = None,
    groundtruth: Trajectory | None = None,
) -> dict[str, Any]:
    """trajectory.txt, mesh.ply, volume_origins.txt, preview.png and report.json in `out`, and
    with loop closure trajectory_uncorrected.txt and trajectory_loops.png (drawn with
    `groundtruth` when given); returns the report. Each file is written atomically, in that
    order, and its name appended to `saved` once in place. A file that cannot be written (a full
    disk, a failed render) is left out and named in the report's "not_saved" with the reason;
    report.json itself must be written (its OSError propagates)."""
    from kintinuous_ref import mesh as meshing
    from kintinuous_ref.datasets.tum import write_trajectory

    saved = [] if saved is None else saved
    not_saved: dict[str, str] = {}
    out.mkdir(parents=True, exist_ok=True)

    def attempt(name: str, write: Callable[[Path], Any]) -> Any:
        try:
            with atomic(out / name) as temporary:
                value = write(temporary)
        except Exception as err:  # kept in the report; the next file is still tried
            not_saved[name] = error_reason(err)
            return None
        saved.append(name)
        return value

    attempt("trajectory.txt", lambda path: write_trajectory(path, result.trajectory))
    closer = result.loop_closer
    if closer is not None:
        _loop_closure_trajectories(result, groundtruth, attempt)
    surface, mesh_size = None, None
    if result.moving is not None and result.volume is not None:
        # The rest of the window is the last slice; the slices merge into one mesh on disk.
        from kintinuous_ref import moving_volume

        try:
            result.moving.finish()
        except Exception as err:  # the last slice is missing, so the mesh would be too
            not_saved["slices"] = not_saved["mesh.ply"] = error_reason(err)
        else:
            if closer is not None:  # every slice's vertices move with the loops closed
                report = {**report, "map_deformation": closer.deform_map(result.moving.store)}
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
                not_saved["preview.png"] = error_reason(err)
    elif result.volume is not None:
        volume = result.volume
        try:
            if result.host_volume is not None:  # a fast backend's volume, as a host TsdfVolume
                volume = result.host_volume(volume)
            contour = result.contour or meshing.marching_cubes  # the backend's, else ref's
            surface = meshing.extract_mesh(volume, contour=contour)
        except Exception as err:
            not_saved["mesh.ply"] = error_reason(err)
        if surface is not None:
            attempt("mesh.ply", lambda path: meshing.write_ply(path, surface))
            if "mesh.ply" in saved:
                mesh_size = (len(surface.points), len(surface.triangles))
    preview_note = None  # why the preview is a plan view, where VTK cannot render
    if preview and surface is not None:
        first = result.poses[0] if result.poses else None
        preview_note = attempt(
            "preview.png", lambda path: meshing.render_preview(surface, path, view_pose=first)
        )
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
    report["warnings"] = [
        *report.get("warnings", []),
        *([preview_note] if preview_note else []),
        *run_warnings(
            result.frames,
            report["fused_frames"],
            result.tracking_failures,
            report["mesh"]["vertices"],
        ),
    ]
    if closer is not None:
        report["loop_closures"] = closer.report()
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


def save_interrupted_report(
    out: Path,
    info: dict[str, Any],
    result: PipelineResult,
    saved: list[str],
    names: list[str],
    signal_name: str,
) -> None:
    """report.json of a save cut short by `signal_name`: how the run ended and which of `names`
    were not saved, so that the folder never holds a trajectory without its report. A further
    signal or a failed write leaves it out (the message then names it among the not saved)."""
    during = f"{signal_name} during the save"
    report = {
        **info,
        "status": "interrupted",
        "reason": f"{result.reason}; {during}" if result.reason else during,
        "last_frame": result.last_frame,
        "frames": result.frames,
        "fused_frames": int(np.sum(result.fused)),
        "tracking_failures": result.tracking_failures,
        "interrupted": True,
        "saved": [*saved, "report.json"],
        "not_saved": {
            name: during for name in names if name not in saved and name != "report.json"
        },
    }
    try:
        write_text_atomic(out / "report.json", strict_dumps(report, indent=2) + "\n")
    except (KeyboardInterrupt, OSError):
        return
    saved.append("report.json")


def _loop_closure_trajectories(
    result: PipelineResult, groundtruth: Trajectory | None, attempt: Callable
) -> None:
    """trajectory_uncorrected.txt (what odometry alone gave) and trajectory_loops.png (both
    from above, with the ground truth when known)."""
    from kintinuous_ref.datasets.tum import write_trajectory
    from kintinuous_ref.loop_closure.figure import draw_trajectories

    closer = result.loop_closer
    timestamps = np.array(result.timestamps)
    uncorrected = Trajectory(timestamps, closer.uncorrected_poses())
    attempt("trajectory_uncorrected.txt", lambda path: write_trajectory(path, uncorrected))
    if not len(timestamps):
        return
    truth = None
    if groundtruth is not None:
        truth = groundtruth.poses[np.array(closer.frames)][:, :3, 3]
        truth = truth if np.isfinite(truth).all() else None
    row = {frame: i for i, frame in enumerate(closer.frames)}
    loops = [(row[c.frame], row[closer.keyframes[c.match].frame]) for c in closer.closures]
    attempt(
        "trajectory_loops.png",
        lambda path: draw_trajectories(
            path, uncorrected.poses[:, :3, 3], result.trajectory.poses[:, :3, 3], truth, loops
        ),
    )
