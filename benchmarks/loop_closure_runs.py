"""Loop closure against the same tracker without it, and against known poses (docs/loop_closure.md).

    python benchmarks/loop_closure_runs.py DATASET OUT [--frames N] [--volume-size S]
        [--resolution N] [--backend cpu] [--no-open3d] [--set KEY=VALUE ...]

DATASET is a TUM folder (a synthetic scenario written by `kintinuous synth`, or real data). Runs
`reconstruct` three times into OUT/closure, OUT/plain and (when the dataset has a scene.ply, the
synthetic ground-truth surface) OUT/groundtruth, and, where open3d is installed, Open3D's
frame-to-model dense SLAM on the same frames with the same voxel size (OUT/open3d, its mesh in
OUT/open3d/mesh.ply; it closes no loops), then prints and writes OUT/summary.json: ATE of
each trajectory (the closure run's corrected and uncorrected ones too) and its return error
(the last pose relative to the first against the truth's), the loop closure report (every
verified candidate's statistics and each closure, with how far apart the ground truth puts the
two keyframes' views), and with
scene.ply the mesh's mean distance to the true surface and the share of its vertices more than
3 cm away (a doubled surface shows there).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import pipeline_vs_open3d  # benchmarks/, beside this file

from kintinuous_ref import metrics, se3
from kintinuous_ref.config import Config, VolumeConfig, with_overrides
from kintinuous_ref.datasets import tum
from kintinuous_ref.loop_closure.calibration import views_apart
from kintinuous_ref.program import reconstruct


def ate(path: Path, truth: tum.Trajectory) -> float:
    errors = metrics.absolute_trajectory_errors(tum.read_trajectory(path), truth)
    return float(np.sqrt(np.mean(errors**2)))


def return_error(path: Path, truth: tum.Trajectory) -> dict[str, float]:
    """How far the last pose relative to the first is from the truth's (translation in metres,
    rotation in degrees): for a sequence that comes back to its start, the error the loop leaves,
    which needs no global accuracy of the ground truth, only at its two ends."""
    poses = tum.read_trajectory(path).poses
    estimated = se3.inverse(poses[0]) @ poses[-1]
    true = se3.inverse(truth.poses[0]) @ truth.poses[len(poses) - 1]
    error = se3.inverse(true) @ estimated
    return {
        "translation_m": float(np.linalg.norm(error[:3, 3])),
        "rotation_deg": float(np.degrees(se3.rotation_angle(error[:3, :3]))),
    }


def truly_apart(frames: list[int], truth: tum.Trajectory) -> dict[str, float]:
    """How far apart the ground truth puts two frames' views (metres, degrees)."""
    metres, degrees = views_apart(truth.poses[frames[0]], truth.poses[frames[1]])
    return {"true_apart_m": metres, "true_apart_deg": degrees}


def with_truth(loops: dict, truth: tum.Trajectory) -> dict:
    """A report's `loop_closures` with each verified candidate and each closure given the true
    distance and angle between its two keyframes' views: which loops join views far apart."""
    return {
        **loops,
        "verified": [{**v, **truly_apart(v["frames"], truth)} for v in loops["verified"]],
        "closures": [{**c, **truly_apart(c["keyframe_frames"], truth)} for c in loops["closures"]],
    }


def mesh_distances(mesh: Path, scene: Path) -> dict[str, float]:
    import pyvista

    from kintinuous_ref import mesh as meshing

    points = np.asarray(pyvista.read(str(mesh)).points, dtype=np.float64)
    distance = meshing.closest_on(pyvista.read(str(scene)), points)[0]
    return {
        "mean_m": float(distance.mean()),
        "median_m": float(np.median(distance)),
        "beyond_3cm": float(np.mean(distance > 0.03)),
    }


def run_open3d(  # noqa: ANN001, PLR0913
    sequence, config: Config, frames: int | None, out: Path, scene: Path, band_voxels: float
) -> dict | None:
    """Open3D's frame-to-model tracker and fusion over the same frames, its truncation band
    `band_voxels` voxels wide (None without open3d). Open3D raises where its tracking fails (a
    singular system); the entry then says so and the other runs stand."""
    out.mkdir(parents=True, exist_ok=True)
    count = frames or len(sequence)
    mesh = out / "mesh.ply"
    voxel_size, max_depth = config.volume.voxel_size, config.preprocess.max_depth
    try:
        row = pipeline_vs_open3d.run_open3d(
            sequence, voxel_size, max_depth, count, mesh, band_voxels
        )
    except RuntimeError as error:
        return {"failed": str(error).strip().splitlines()[-1]}
    if row is None:
        return None
    entry: dict = {"ate_m": row["ate_mm"] / 1000.0}
    if scene.exists():
        entry["mesh"] = mesh_distances(mesh, scene)
    return entry


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("dataset", type=Path)
    parser.add_argument("out", type=Path)
    parser.add_argument("--frames", type=int)
    parser.add_argument("--volume-size", type=float, default=4.0)
    parser.add_argument("--resolution", type=int, default=128)
    parser.add_argument("--backend", default="cpu")
    parser.add_argument("--no-open3d", action="store_true", help="our two runs only")
    parser.add_argument(
        "--set", action="append", default=[], metavar="KEY=VALUE", help="a configuration value"
    )
    args = parser.parse_args()
    sequence = tum.open_sequence(args.dataset)
    truth = sequence.groundtruth_for_frames()
    config = Config(volume=VolumeConfig(size=args.volume_size, resolution=args.resolution))
    overrides = dict(item.split("=", 1) for item in args.set)
    config = with_overrides(config, {key: json.loads(value) if value[:1] in "0123456789-[tf"
                                     else value for key, value in overrides.items()})  # fmt: skip
    scene = args.dataset / "scene.ply"
    runs = [("closure", "icp+rgbd", True), ("plain", "icp+rgbd", False)]
    if scene.exists():
        runs.append(("groundtruth", "groundtruth", False))
    summary: dict = {}
    for name, odometry, closing in runs:
        out = args.out / name
        report = reconstruct.reconstruct(
            sequence, out, config, odometry, count=args.frames, backend_name=args.backend,
            show_progress=False, overwrite=True, loop_closure=closing,
        )  # fmt: skip
        trajectory = out / "trajectory.txt"
        entry: dict = {"ate_m": ate(trajectory, truth), "return": return_error(trajectory, truth)}
        if closing:
            uncorrected = out / "trajectory_uncorrected.txt"
            entry["ate_uncorrected_m"] = ate(uncorrected, truth)
            entry["return_uncorrected"] = return_error(uncorrected, truth)
            entry["loop_closures"] = with_truth(report["loop_closures"], truth)
            entry["map_deformation"] = report.get("map_deformation")
            entry["loop_closure_ms"] = report["timing_ms"].get("loop_closure")
        if scene.exists():
            entry["mesh"] = mesh_distances(out / "mesh.ply", scene)
        summary[name] = entry
        print(name, json.dumps(entry, indent=1))
        write_summary(args.out, summary)
    # Open3D's default band (8 voxels) and ours (config.volume.truncation)
    our_band = config.volume.truncation / config.volume.voxel_size
    bands = () if args.no_open3d else (("open3d", 8.0), ("open3d_our_band", our_band))
    for name, band_voxels in bands:
        entry = run_open3d(sequence, config, args.frames, args.out / name, scene, band_voxels)
        if entry is not None:
            summary[name] = entry
            print(name, json.dumps(entry, indent=1))
            write_summary(args.out, summary)


def write_summary(out: Path, summary: dict) -> None:
    """OUT/summary.json after every run, so that a run that fails later loses none of it."""
    (out / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")


if __name__ == "__main__":
    main()
