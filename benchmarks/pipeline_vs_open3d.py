"""The whole pipeline, per stage, against Open3D's frame-to-model dense SLAM, in one run.

    .venv/bin/python benchmarks/pipeline_vs_open3d.py [--frames 30] [--ref-frames 4]
        [--backends cpu,ref] [--rounds 1] [--threads N] [--json out.json] [--plot stages.png]

Ours: `kintinuous_ref.pipeline.run` (icp+rgbd, 640x480, 256^3 over 3 m, the moving volume,
raycast every frame) on each backend, plus the cpu backend with the "fast odometry" setting
(finest pyramid level skipped: 0/5/4 iterations instead of 10/5/4, finest first) and with
Open3D's schedule (1/3/6). The reference runs only `--ref-frames` frames (seconds each).
Open3D: `o3d.t.pipelines.slam.Model` on the CPU with the voxel size of our volume (11.7 mm),
per frame track_frame_to_model (its point-to-plane ICP; iterations 6/3/1 coarsest first, so one
at full resolution, and it stops a level early once converged), integrate and
synthesize_model_frame (its raycast), timed stage by stage. Both start at the first ground-truth
pose; accuracy is the ATE RMSE over the frames run (rigidly aligned, kintinuous_ref.metrics).
Stage times are medians over frames 2..N (the first frame compiles and has nothing to track).
Open3D runs right after our default column, and `--rounds R` repeats both (and the other
columns but the reference) R times, pooling the frames: a noisy host then slows both sides
alike, and the ratios of each round are printed too. From the second round on, the two swap
places every round (Open3D right before our default column in rounds 2, 4, ...), so that
neither side always runs first in the process or right after the other. `--threads N` runs
both on N threads (numba's thread count, and OpenMP's, which Open3D's CPU kernels use); the
default is each library's own (every core). `--default-only` leaves out the fast-odometry and
1/3/6 columns; `--converged-steps 1e-4,3e-4` adds a cpu column for each of those early-stop
thresholds (`tracking.converged_step`: a level ends at a step shorter than it; 1e-5 by
default).
The row "odometry cpu" is the odometry's CPU time per frame (the process's, every thread's:
on one thread what the odometry's work costs, which other jobs on the machine disturb far
less than its wall time).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import replace
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # as the kintinuous command (cli.py)

import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from kintinuous_fast import load_backend  # noqa: E402
from kintinuous_ref import metrics, pipeline  # noqa: E402
from kintinuous_ref.config import Config, fast_odometry  # noqa: E402
from kintinuous_ref.datasets import data_folder  # noqa: E402
from kintinuous_ref.datasets.tum import Trajectory, open_sequence  # noqa: E402

REDKITCHEN = data_folder() / "redkitchen"  # $KINTINUOUS_DATA, else ../shared/data
# track_frame_to_model's default schedule, finest level first as in our Config: Open3D lists it
# coarsest first, (6, 3, 1), and so runs one iteration at full resolution.
OPEN3D_ITERATIONS = (1, 3, 6)
STAGES = ("preprocess", "odometry", "integrate", "raycast", "total")
# Rows beside the stages: the odometry's process CPU time per frame.
CPU_ROWS = ("odometry cpu",)
STAGE_COLOURS = ("#8da0cb", "#fc8d62", "#66c2a5", "#e78ac3")  # of the four stages in the plot


def ate_mm(poses: list[np.ndarray], groundtruth: Trajectory, count: int) -> float:
    stamps = groundtruth.timestamps[:count]
    estimate = Trajectory(stamps, np.asarray(poses))
    errors = metrics.absolute_trajectory_errors(
        estimate, Trajectory(stamps, groundtruth.poses[:count])
    )
    return 1000.0 * float(np.sqrt(np.mean(errors**2)))


def open3d_iterations(config: Config) -> Config:
    """`config` with Open3D's iteration schedule for the joint tracker (1/3/6 finest first): the
    same passes over each pyramid level as its tracker, with two cost terms to its one."""
    rgbd = replace(config.rgbd, combined_iterations=OPEN3D_ITERATIONS)
    return replace(config, rgbd=rgbd)


def stop_at(config: Config, step: float) -> Config:
    """`config` with a level of the dense trackers ending at a step shorter than `step`
    (tracking.converged_step; the default is 1e-5)."""
    return replace(config, tracking=replace(config.tracking, converged_step=step))


def run_ours(sequence, backend: str, config: Config, frames: int) -> dict:  # noqa: ANN001
    """Per stage the times of frames 2..N (lists), with `ate_mm` and `failures`; on the cpu
    backend also the odometry's CPU time ("odometry cpu", of its dense estimates)."""
    groundtruth = sequence.groundtruth_for_frames()
    chosen = load_backend(backend)
    with odometry_cpu_time(chosen) as cpu_ms:
        result = pipeline.run(
            sequence.frames(0, frames),
            sequence.camera,
            config,
            "icp+rgbd",
            groundtruth,
            backend=chosen,
            predict_model=True,
        )
    row = {stage: list(result.timings_ms[stage][1:]) for stage in STAGES}
    if cpu_ms:
        row["odometry cpu"] = cpu_ms
    row["ate_mm"] = ate_mm(result.poses, groundtruth, frames)
    row["failures"] = result.tracking_failures
    return row


@contextmanager
def odometry_cpu_time(backend) -> Iterator[list[float]]:  # noqa: ANN001
    """A list that collects the process CPU ms of each dense estimate but the first while the
    block runs (the backend's odometry module's estimate_dense, timed around); empty where the
    backend has no such module."""
    systems = getattr(backend, "odometry", None)
    untimed = getattr(systems, "estimate_dense", None)
    laps: list[float] = []
    if untimed is None:
        yield laps
        return

    def timed(*args, **options):  # noqa: ANN002, ANN003, ANN202
        started = time.process_time()
        try:
            return untimed(*args, **options)
        finally:
            laps.append(1000.0 * (time.process_time() - started))

    systems.estimate_dense = timed
    try:
        yield laps
    finally:
        systems.estimate_dense = untimed
        del laps[:1]  # the first estimate (frame 1) warms up, as the stages' first frame


def run_open3d(  # noqa: ANN001, PLR0913
    sequence,
    voxel_size: float,
    max_depth: float,
    frames: int,
    mesh: Path | None = None,
    truncation_voxels: float = 8.0,
) -> dict | None:
    """As run_ours, for Open3D's dense SLAM (None without open3d), its truncation band
    `truncation_voxels` voxels wide (8: Open3D's default); with `mesh`, its model's triangle
    mesh (in world coordinates, as ours) is written there too."""
    try:
        import open3d as o3d
        import open3d.core as o3c
    except ImportError:
        return None
    camera = sequence.camera
    device = o3c.Device("CPU:0")
    intrinsic = o3c.Tensor(camera.matrix, o3c.Dtype.Float64)
    groundtruth = sequence.groundtruth_for_frames()
    first = groundtruth.poses[0]
    # Open3D keeps camera-to-model poses starting at identity; ours are world poses.
    model = o3d.t.pipelines.slam.Model(voxel_size, 16, 40000, o3c.Tensor(np.eye(4)), device)
    current = o3d.t.pipelines.slam.Frame(camera.height, camera.width, intrinsic, device)
    predicted = o3d.t.pipelines.slam.Frame(camera.height, camera.width, intrinsic, device)
    to_model = np.eye(4)
    laps = {stage: [] for stage in ("odometry", "odometry cpu", "integrate", "raycast", "total")}
    poses = []
    for index, frame in enumerate(sequence.frames(0, frames)):
        raw = np.round(frame.depth * camera.depth_scale).astype(np.uint16)
        current.set_data_from_image("depth", o3d.t.geometry.Image(o3c.Tensor(raw)))
        current.set_data_from_image("color", o3d.t.geometry.Image(o3c.Tensor(frame.colour)))
        start, cpu_start = time.perf_counter(), time.process_time()
        if index > 0:
            tracked = model.track_frame_to_model(
                current, predicted, camera.depth_scale, max_depth, 0.07
            )
            to_model = to_model @ tracked.transformation.numpy()
        tracked_at, tracked_cpu = time.perf_counter(), time.process_time()
        model.update_frame_pose(index, o3c.Tensor(to_model))
        model.integrate(current, camera.depth_scale, max_depth, truncation_voxels)
        integrated_at = time.perf_counter()
        model.synthesize_model_frame(
            predicted, camera.depth_scale, 0.1, max_depth, truncation_voxels, False
        )
        end = time.perf_counter()
        if index > 0:
            laps["odometry"].append(1000.0 * (tracked_at - start))
            laps["odometry cpu"].append(1000.0 * (tracked_cpu - cpu_start))
            laps["integrate"].append(1000.0 * (integrated_at - tracked_at))
            laps["raycast"].append(1000.0 * (end - integrated_at))
            laps["total"].append(1000.0 * (end - start))
        poses.append(first @ to_model)
    row: dict = dict(laps)
    row["ate_mm"] = ate_mm(poses, groundtruth, frames)
    if mesh is not None:
        surface = model.extract_trianglemesh().to_legacy().transform(first)
        o3d.io.write_triangle_mesh(str(mesh), surface)
    return row


def run_columns(  # noqa: ANN001
    sequence, config: Config, args: argparse.Namespace, with_reference: bool, open3d_first: bool
) -> dict:
    """One round: each backend's column (the cpu one followed at once by Open3D's, or
    preceded by it `open3d_first`, then the cpu variants); the reference only
    `with_reference`."""
    runs: dict[str, dict] = {}

    def add_open3d() -> None:
        row = run_open3d(
            sequence, config.volume.voxel_size, config.preprocess.max_depth, args.frames
        )
        if row is not None:
            runs["open3d"] = row

    backends = [name for name in args.backends.split(",") if name]
    for backend in backends:
        if backend == "ref" and not with_reference:
            continue
        frames = args.ref_frames if backend == "ref" else args.frames
        if backend == "cpu" and open3d_first:
            add_open3d()
        runs[backend] = run_ours(sequence, backend, config, frames)
        if backend == "cpu":
            if not open3d_first:
                add_open3d()
            for step in args.converged_steps:
                stopping = stop_at(config, step)
                runs[f"cpu stop {step:g}"] = run_ours(sequence, "cpu", stopping, frames)
            if args.default_only:
                continue
            runs["cpu fast-odo"] = run_ours(sequence, "cpu", fast_odometry(config), frames)
            runs["cpu 1/3/6"] = run_ours(sequence, "cpu", open3d_iterations(config), frames)
    if "cpu" not in backends:
        add_open3d()
    # Open3D's column last, as before
    return {name: runs[name] for name in sorted(runs, key=lambda name: name == "open3d")}


def medians(row: dict) -> dict:
    """Lists of frame times to their medians; other entries as they are."""
    return {
        key: statistics.median(value) if isinstance(value, list) else value
        for key, value in row.items()
    }


def print_round_ratios(rounds: list[dict[str, dict]]) -> None:
    """Per round, ours / Open3D's medians of the default column (the spread of the noise)."""
    print("cpu / Open3D in each round:")
    for stage in ("odometry", "odometry cpu", "integrate", "raycast", "total"):
        ratios = [
            statistics.median(runs["cpu"][stage]) / statistics.median(runs["open3d"][stage])
            for runs in rounds
            if stage in runs.get("cpu", {}) and stage in runs.get("open3d", {})
        ]
        print(f"  {stage:10s} " + " ".join(f"{ratio:.2f}" for ratio in ratios))


def print_table(table: dict[str, dict]) -> None:
    names = list(table)
    print(f"{'stage (median ms)':20s}" + "".join(f"{name:>14s}" for name in names))
    for stage in (*STAGES, *CPU_ROWS, "fps", "ate_mm"):
        cells = []
        for name in names:
            row = table[name]
            value = 1000.0 / row["total"] if stage == "fps" else row.get(stage)
            cells.append(f"{value:14.1f}" if value is not None else f"{'-':>14s}")
        print(f"{stage:20s}" + "".join(cells))
    if "open3d" in table:
        print("ratio to Open3D (ours / theirs; < 1 = ours faster):")
        for name in names:
            if name != "open3d":
                ratios = {
                    stage: table[name][stage] / table["open3d"][stage]
                    for stage in ("odometry", "integrate", "raycast", "total")
                }
                print(f"  {name:12s} " + "  ".join(f"{k} {v:.2f}" for k, v in ratios.items()))


def plot_stages(table: dict[str, dict], path: Path, rounds: int = 1) -> None:
    """Stacked bars of the per-stage medians of every column but the reference (off the scale:
    its total is in the title), with the 10 frames/s budget marked."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = [name for name in table if name != "ref"]
    figure, axes = plt.subplots(figsize=(7.5, 1.3 + 0.7 * len(names)))
    for index, name in enumerate(names):
        left = 0.0
        for stage, colour in zip(STAGES[:-1], STAGE_COLOURS, strict=True):
            value = table[name].get(stage) or 0.0
            axes.barh(index, value, left=left, color=colour, label=stage if index == 0 else None)
            left += value
        axes.text(left + 2, index, f"{1000.0 / table[name]['total']:.1f} frames/s", va="center")
    axes.axvline(100.0, color="black", linestyle=":", linewidth=1)
    axes.text(101, -0.45, "10 frames/s", fontsize=8, va="top")
    axes.set_yticks(range(len(names)), names)
    axes.invert_yaxis()
    axes.set_xlabel("median ms per frame (redkitchen 640x480, icp+rgbd, 256^3)")
    title = "per-stage time, one run" if rounds == 1 else f"per-stage time, {rounds} rounds"
    if "ref" in table:
        title += f" (the NumPy reference: {table['ref']['total']:.0f} ms per frame)"
    axes.set_title(title, fontsize=10)
    axes.legend(ncol=4, fontsize=8, loc="upper center", bbox_to_anchor=(0.5, -0.3), frameon=False)
    figure.tight_layout()
    figure.savefig(path, dpi=110)


def set_threads(count: int | None) -> str:
    """Run both pipelines on `count` threads (None: leave each library's default) and say how
    many each uses. OpenMP reads its variable when Open3D loads it, which is later."""
    import numba

    if count is not None:
        if not 1 <= count <= numba.config.NUMBA_NUM_THREADS:
            sys.exit(f"--threads must be in 1..{numba.config.NUMBA_NUM_THREADS}, got {count}")
        numba.set_num_threads(count)
        os.environ["OMP_NUM_THREADS"] = str(count)
    openmp = os.environ.get("OMP_NUM_THREADS", f"OpenMP's default ({os.cpu_count()})")
    return f"ours {numba.get_num_threads()}, Open3D {openmp}"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=30)
    parser.add_argument("--ref-frames", type=int, default=4)
    parser.add_argument("--backends", default="cpu,ref")
    parser.add_argument("--rounds", type=int, default=1, help="repeat every column but ref")
    parser.add_argument("--json", type=Path)
    parser.add_argument("--plot", type=Path, help="write a bar chart of the stages (PNG)")
    parser.add_argument("--threads", type=int, help="threads for both (default: every core)")
    parser.add_argument(
        "--default-only", action="store_true", help="no fast-odometry or 1/3/6 columns"
    )
    parser.add_argument(
        "--converged-steps",
        type=lambda text: [float(value) for value in text.split(",") if value],
        default=[],
        help="comma-separated tracking.converged_step values: a cpu column for each, run after "
        "Open3D's",
    )
    args = parser.parse_args()
    threads = set_threads(args.threads)
    if not REDKITCHEN.is_dir():
        sys.exit(f"{REDKITCHEN}: not found (the benchmark needs the redkitchen sequence)")
    sequence = open_sequence(REDKITCHEN)
    config = Config()  # 256^3 over 3 m
    print(
        f"redkitchen 640x480, {args.frames} frames, icp+rgbd, 256^3 over 3 m; "
        f"{platform.machine()}, {os.cpu_count()} cores, Python {platform.python_version()}, "
        f"load average {os.getloadavg()[0]:.1f}; threads: {threads}"
    )
    pooled: dict[str, dict] = {}
    rounds: list[dict[str, dict]] = []
    for round_index in range(args.rounds):
        runs = run_columns(
            sequence, config, args, round_index == 0, open3d_first=round_index % 2 == 1
        )
        rounds.append(runs)
        for name, row in runs.items():
            into = pooled.setdefault(name, {"ate_mm": row["ate_mm"]})
            for stage, values in row.items():
                if isinstance(values, list):
                    into.setdefault(stage, []).extend(values)
            if "failures" in row:
                into["failures"] = into.get("failures", 0) + row["failures"]
    table = {name: medians(row) for name, row in pooled.items()}
    print_table(table)
    if args.rounds > 1 and "open3d" in table:
        print_round_ratios(rounds)
    print(f"load average after: {os.getloadavg()[0]:.1f}")
    if args.json:
        args.json.write_text(json.dumps(table, indent=2) + "\n")
    if args.plot:
        plot_stages(table, args.plot, args.rounds)


if __name__ == "__main__":
    main()
