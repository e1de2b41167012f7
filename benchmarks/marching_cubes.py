"""Our marching cubes (kintinuous_ref.marching_cubes, and the cpu backend's) against VTK's flying
edges on the same fused volume: triangle counts, the symmetric mean distance between the
surfaces in voxels, and the time each takes.

    .venv/bin/python benchmarks/marching_cubes.py [--scenario desk] [--frames 60]
        [--resolution 256] [--size 3.0] [--repeat 3] [--out results/marching_cubes.json]

The volume is the scenario fused with its true poses by the cpu backend, seen as the
reference's TsdfVolume (Backend.host_volume). VTK's mesh is filtered by the rule of ours (a
vertex kept when both voxels of its edge are observed), so both describe observed space only.
Times are the best of --repeat rounds after one warm-up call each (numba compiles on its
first); each round runs every method once, in turn, so that on a busy machine all see the same
load. The load average (1, 5, 15 minutes) before and after the timings is part of the output.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import time
from pathlib import Path

import numpy as np
import pyvista

from kintinuous_fast import load_backend
from kintinuous_fast.mesh import cpu as cpu_mesh
from kintinuous_ref import marching_cubes as reference
from kintinuous_ref.config import Config, VolumeConfig
from kintinuous_ref.program.reconstruct import open_dataset
from kintinuous_ref.tsdf import TsdfVolume

# Vertices per mesh that the distance samples (closest-point queries on the other mesh).
DISTANCE_SAMPLES = 200_000


def fused_volume(scenario: str, frames: int, resolution: int, size: float) -> TsdfVolume:
    """The scenario's first `frames` frames fused with true poses (cpu backend), on the host."""
    sequence = open_dataset(scenario, progress=True, frames_needed=frames)
    poses = sequence.groundtruth_for_frames().poses
    config = Config(volume=VolumeConfig(resolution=resolution, size=size, moving=False))
    backend = load_backend("cpu")
    volume = backend.tsdf.make_volume(config.volume, poses[0], config.colour.max_weight)
    for frame in sequence.frames(0, min(frames, len(sequence))):
        current = backend.preprocess.preprocess_frame(
            frame.colour, frame.depth, sequence.camera, config.preprocess
        )
        weights = backend.colour.colour_weights(current, config.colour)
        pose = poses[frame.index]
        backend.tsdf.integrate(
            volume, current.depth, pose, sequence.camera, current.colour, weights
        )
    return backend.host_volume(volume)


def vtk_grid(tsdf: np.ndarray) -> pyvista.ImageData:
    """The volume as VTK's image (index units; VTK orders points x fastest)."""
    grid = pyvista.ImageData(dimensions=tsdf.shape)
    grid.point_data["tsdf"] = tsdf.ravel(order="F")
    return grid


def vtk_contour(grid: pyvista.ImageData) -> pyvista.PolyData:
    return grid.contour([0.0], scalars="tsdf", method="flying_edges", compute_normals=False)


def vtk_marching_cubes(tsdf: np.ndarray, weight: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """VTK's flying edges on the volume, its vertices filtered by our rule: the whole path
    that meshing took through VTK (copy into VTK's order, contour, filter)."""
    surface = vtk_contour(vtk_grid(tsdf))
    points = np.asarray(surface.points, dtype=np.float64)
    triangles = surface.faces.reshape(-1, 4)[:, 1:].astype(np.int64)
    lower = np.floor(points).astype(np.int64)
    upper = np.minimum(np.ceil(points).astype(np.int64), np.array(tsdf.shape) - 1)
    observed = weight > 0
    keep = observed[tuple(lower.T)] & observed[tuple(upper.T)]
    return points, triangles[keep[triangles].all(axis=1)]


def best_ms(calls: dict[str, tuple], repeat: int) -> dict[str, float]:
    """The best time (ms) of each of `calls` (name: (function, *args)) over `repeat` rounds,
    after one warm-up call each (numba compiles, caches settle). Each round calls every
    function once, in turn, so that on a busy machine all of them see the same load."""
    for function, *args in calls.values():
        function(*args)
    times: dict[str, list[float]] = {name: [] for name in calls}
    for _ in range(repeat):
        for name, (function, *args) in calls.items():
            started = time.perf_counter()
            function(*args)
            times[name].append(time.perf_counter() - started)
    return {name: 1000 * min(taken) for name, taken in times.items()}


def mean_distance(points: np.ndarray, vertices: np.ndarray, triangles: np.ndarray) -> float:
    """Mean distance (voxels) from up to DISTANCE_SAMPLES of `points` to the triangle mesh."""
    rng = np.random.default_rng(0)
    chosen = points[rng.choice(len(points), min(len(points), DISTANCE_SAMPLES), replace=False)]
    cells = np.column_stack([np.full(len(triangles), 3), triangles]).ravel()
    surface = pyvista.PolyData(vertices, cells)
    _, closest = surface.find_closest_cell(chosen, return_closest_point=True)
    return float(np.linalg.norm(chosen - closest, axis=1).mean())


def cpu_model() -> str:
    """The CPU's model name (/proc/cpuinfo) and how many CPUs this process may use."""
    try:
        lines = Path("/proc/cpuinfo").read_text().splitlines()
        model = next(line.split(":", 1)[1].strip() for line in lines if "model name" in line)
    except (OSError, StopIteration):
        model = platform.processor() or platform.machine()
    return f"{model}, {len(os.sched_getaffinity(0))} CPUs"


def used_points(vertices: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    return vertices[np.unique(triangles)]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenario", default="desk")
    parser.add_argument("--frames", type=int, default=60)
    parser.add_argument("--resolution", type=int, default=256)
    parser.add_argument("--size", type=float, default=3.0)
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--out", type=Path, default=Path("results/marching_cubes.json"))
    args = parser.parse_args()

    import numba

    host = fused_volume(args.scenario, args.frames, args.resolution, args.size)
    tsdf, weight = host.logical(host.tsdf), host.logical(host.weight)
    ours = reference.marching_cubes(tsdf, weight, 0.0)
    fast = cpu_mesh.marching_cubes(tsdf, weight, 0.0)
    theirs = vtk_marching_cubes(tsdf, weight)
    results = {
        "date": datetime.date.today().isoformat(),
        "machine": cpu_model(),
        "threads": numba.get_num_threads(),
        "scenario": args.scenario,
        "frames": args.frames,
        "resolution": args.resolution,
        "triangles": {"ref": len(ours[1]), "cpu": len(fast[1]), "vtk": len(theirs[1])},
        "vertices": {"ref": len(ours[0]), "vtk": len(np.unique(theirs[1]))},
        "cpu_equals_ref": bool(
            np.array_equal(ours[0], fast[0]) and np.array_equal(ours[1], fast[1])
        ),
        "mean_distance_voxels": {
            "ref_to_vtk": mean_distance(used_points(*ours), *theirs),
            "vtk_to_ref": mean_distance(used_points(*theirs), *ours),
        },
    }
    results["load_average_before"] = os.getloadavg()
    results["ms"] = best_ms(
        {
            "ref": (reference.marching_cubes, tsdf, weight, 0.0),
            "cpu": (cpu_mesh.marching_cubes, tsdf, weight, 0.0),
            "vtk": (vtk_marching_cubes, tsdf, weight),
            "vtk_contour_only": (vtk_contour, vtk_grid(tsdf)),
        },
        args.repeat,
    )
    results["load_average_after"] = os.getloadavg()
    print(json.dumps(results, indent=2))
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(results, indent=2) + "\n")


if __name__ == "__main__":
    main()
