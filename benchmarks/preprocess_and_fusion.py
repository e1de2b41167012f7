"""Per-stage milliseconds at 640x480: kintinuous_ref (NumPy) against kintinuous_fast's backends,
and Open3D's TSDF integration / raycasting where `open3d` is installed (benchmark only).

    .venv/bin/python benchmarks/preprocess_and_fusion.py [--runs 5] [--resolution 256]
        [--backends ref,cpu] [--frames N] [--json out.json]

Frames: the real redkitchen sequence from $KINTINUOUS_DATA (else ../shared/data) when present,
else a synthetic scene.
Each stage is run once to warm up (numba compiles, caches fill), then `--runs` times; the median
is reported. Integration fuses a sequence of frames at their ground-truth poses into a fresh
volume of `--resolution`^3 over 3 m (the default config) and times every frame after the first.
"""

from __future__ import annotations

import argparse
import json
import platform
import statistics
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from kintinuous_fast import load_backend  # noqa: E402
from kintinuous_fast.tsdf.volume import to_reference_volume  # noqa: E402
from kintinuous_ref.colour import colour_weights  # noqa: E402
from kintinuous_ref.config import Config, VolumeConfig  # noqa: E402
from kintinuous_ref.datasets import data_folder  # noqa: E402

REDKITCHEN = data_folder() / "redkitchen"  # $KINTINUOUS_DATA, else ../shared/data


def load_frames(count: int) -> tuple[list, list, object, str]:
    """(colours, raw depths, poses, camera, source name) of `count` consecutive frames."""
    if REDKITCHEN.is_dir():
        from kintinuous_ref.datasets.tum import open_sequence

        sequence = open_sequence(REDKITCHEN)
        frames = list(sequence.frames(0, count))
        poses = sequence.groundtruth_for_frames().poses[:count]
        depths = [np.round(f.depth * 5000.0).astype(np.uint16) for f in frames]
        return [f.colour for f in frames], depths, poses, sequence.camera, "redkitchen"
    from kintinuous_ref.datasets.synthetic import make_scenario

    scenario = make_scenario("desk", frames=count)
    rendered = [scenario.render(i) for i in range(count)]
    depths = [np.round(d * 5000.0).astype(np.uint16) for _, d in rendered]
    return [c for c, _ in rendered], depths, scenario.trajectory.poses, scenario.camera, "desk"


def median_ms(function, runs: int) -> float:  # noqa: ANN001
    function()  # warm-up: compilation, caches
    times = []
    for _ in range(runs):
        start = time.perf_counter()
        function()
        times.append(1000.0 * (time.perf_counter() - start))
    return statistics.median(times)


def bench_backend(name: str, data: tuple, config: Config, runs: int) -> dict[str, float]:
    colours, depths, poses, camera, _ = data
    backend = load_backend(name)
    pp, cfg = backend.preprocess, config.preprocess
    results = {}
    raw = pp.metric_depth(depths[0], cfg.max_depth, camera.depth_scale)
    filtered = pp.bilateral_filter(
        raw, cfg.bilateral_sigma_space, cfg.bilateral_sigma_depth, cfg.bilateral_radius
    )
    intensity = pp.intensity_image(colours[0])
    vertices = pp.vertex_map(filtered, camera)
    results["bilateral_filter"] = median_ms(
        lambda: pp.bilateral_filter(
            raw, cfg.bilateral_sigma_space, cfg.bilateral_sigma_depth, cfg.bilateral_radius
        ),
        runs,
    )
    results["pyramid_down_depth"] = median_ms(
        lambda: pp.pyramid_down_depth(raw, cfg.pyramid_depth_cutoff), runs
    )
    results["vertex+normal_map"] = median_ms(
        lambda: pp.normal_map(pp.vertex_map(filtered, camera)), runs
    )
    results["intensity_gradients"] = median_ms(
        lambda: pp.intensity_gradients(intensity, cfg.gradient_blur_sigma), runs
    )
    results["discontinuity_mask"] = median_ms(
        lambda: pp.discontinuity_mask(
            raw, cfg.discontinuity_window, cfg.discontinuity_jump, cfg.discontinuity_max_bad
        ),
        runs,
    )
    results["preprocess_frame"] = median_ms(
        lambda: pp.preprocess_frame(colours[0], depths[0], camera, cfg), runs
    )
    del vertices

    # Integration: frames preprocessed once (with the reference, shared by every backend).
    from kintinuous_ref.preprocess import preprocess_frame

    prepared = [preprocess_frame(c, d, camera, cfg) for c, d in zip(colours, depths, strict=True)]
    weights = [colour_weights(frame, config.colour) for frame in prepared]
    volume = backend.tsdf.make_volume(config.volume, poses[0], config.colour.max_weight)
    times = []
    for index, frame in enumerate(prepared):
        start = time.perf_counter()
        backend.tsdf.integrate(
            volume, frame.depth, poses[index], camera, frame.colour, weights[index]
        )
        if index > 0:  # the first call compiles
            times.append(1000.0 * (time.perf_counter() - start))
    results["integrate"] = statistics.median(times)
    last = poses[len(prepared) - 1]
    results["raycast"] = median_ms(lambda: backend.raycast.raycast(volume, last, camera), runs)
    results["_volume"] = volume
    return results


def bench_open3d(data: tuple, config: Config, runs: int) -> dict[str, float] | None:
    """Open3D's VoxelBlockGrid (tensor API, CPU): integrate and ray_cast with the same truncation
    and voxel size. Its volume is sparse (hashed 8^3 blocks), ours dense: a point of comparison,
    not the same algorithm."""
    try:
        import open3d as o3d
        import open3d.core as o3c
    except ImportError:
        return None
    colours, depths, poses, camera, _ = data
    device = o3c.Device("CPU:0")
    intrinsic = o3c.Tensor(camera.matrix, o3c.Dtype.Float64)
    grid = o3d.t.geometry.VoxelBlockGrid(
        attr_names=("tsdf", "weight", "color"),
        attr_dtypes=(o3c.float32, o3c.float32, o3c.float32),
        attr_channels=((1), (1), (3)),
        voxel_size=config.volume.voxel_size,
        block_resolution=8,
        block_count=100000,
        device=device,
    )
    times = []
    for index, (colour, depth) in enumerate(zip(colours, depths, strict=True)):
        extrinsic = o3c.Tensor(np.linalg.inv(poses[index]), o3c.Dtype.Float64)
        depth_image = o3d.t.geometry.Image(o3c.Tensor(depth)).to(device)
        colour_image = o3d.t.geometry.Image(o3c.Tensor(colour)).to(device)
        start = time.perf_counter()
        blocks = grid.compute_unique_block_coordinates(
            depth_image,
            intrinsic,
            extrinsic,
            camera.depth_scale,
            config.preprocess.max_depth,
            config.volume.truncation,
        )
        grid.integrate(
            blocks,
            depth_image,
            colour_image,
            intrinsic,
            extrinsic,
            camera.depth_scale,
            config.preprocess.max_depth,
            config.volume.truncation,
        )
        if index > 0:
            times.append(1000.0 * (time.perf_counter() - start))
    last = o3c.Tensor(np.linalg.inv(poses[len(depths) - 1]), o3c.Dtype.Float64)

    def cast() -> None:
        blocks = grid.compute_unique_block_coordinates(
            o3d.t.geometry.Image(o3c.Tensor(depths[-1])),
            intrinsic,
            last,
            camera.depth_scale,
            config.preprocess.max_depth,
            config.volume.truncation,
        )
        grid.ray_cast(
            blocks,
            intrinsic,
            last,
            camera.width,
            camera.height,
            ["depth", "normal", "color"],
            camera.depth_scale,
            0.1,
            config.preprocess.max_depth,
            min(0.8 * config.volume.truncation, 1.0),
        )

    return {"integrate": statistics.median(times), "raycast": median_ms(cast, runs)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=5)
    parser.add_argument("--frames", type=int, default=6, help="frames fused for integration")
    parser.add_argument("--resolution", type=int, default=256)
    parser.add_argument("--backends", default="ref,cpu")
    parser.add_argument("--json", type=Path)
    args = parser.parse_args()
    config = Config(volume=VolumeConfig(resolution=args.resolution, size=3.0))
    data = load_frames(args.frames)
    print(f"{data[4]} 640x480, {args.resolution}^3 volume over 3 m, median of {args.runs} runs")
    print(f"machine: {platform.processor() or platform.machine()}, {platform.python_version()}")
    table: dict[str, dict[str, float]] = {}
    volumes = {}
    for name in [n for n in args.backends.split(",") if n]:
        results = bench_backend(name, data, config, args.runs)
        volumes[name] = results.pop("_volume")
        table[name] = results
    open3d_results = bench_open3d(data, config, args.runs)
    if open3d_results is not None:
        table["open3d"] = open3d_results
    stages = list(next(iter(table.values())))
    print(f"{'stage':22s}" + "".join(f"{name:>12s}" for name in table))
    for stage in stages:
        cells = "".join(
            f"{table[name][stage]:12.1f}" if stage in table[name] else f"{'-':>12s}"
            for name in table
        )
        print(f"{stage:22s}{cells}")
    if "cpu" in volumes and "ref" in volumes:  # the two volumes agree (the tests' claim, at scale)
        fast, reference = to_reference_volume(volumes["cpu"]), volumes["ref"]
        observed = reference.weight > 0
        print(
            f"cpu vs ref volume after {args.frames} frames: weights equal "
            f"{np.array_equal(fast.weight, reference.weight)}, max |dF| "
            f"{np.abs(fast.tsdf - reference.tsdf)[observed].max() * 32767:.2f} / 32767"
        )
    if args.json:
        args.json.write_text(json.dumps(table, indent=2))


if __name__ == "__main__":
    main()
