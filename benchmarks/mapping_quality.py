"""Mapping quality with known poses: geometry and colour of a fused synthetic scene against its
true surface (scene.ply), with and without colour artifact reduction (paper VI-B).

    .venv/bin/python benchmarks/mapping_quality.py [--scenario desk] [--frames 300]
        [--resolution 256] [--size 3.0] [--out results/mapping_quality.json]

Both colour settings are fused in one pass over the frames (the geometry is identical: colour
weights never touch the TSDF), so the frames are read and preprocessed once.

Geometry: accuracy = mean distance from the mesh's vertices to the true surface; completeness =
share of true-surface samples (1 cm apart) that some camera of the run saw (within 2 cm of its
depth map) and that lie inside the volume, which are within 1 cm of the mesh.
Colour: mean absolute per-channel error (0..255) of coloured mesh vertices against the true colour
at their closest true-surface point, and the share of vertices without any colour.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
import pyvista
from tqdm import tqdm

from kintinuous_ref import colour, mesh, preprocess, tsdf
from kintinuous_ref.config import ColourConfig, Config, VolumeConfig
from kintinuous_ref.program.reconstruct import open_dataset


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenario", default="desk")
    parser.add_argument("--frames", type=int, default=300)
    parser.add_argument("--resolution", type=int, default=256)
    parser.add_argument("--size", type=float, default=3.0)
    parser.add_argument("--out", type=Path, default=Path("results/mapping_quality.json"))
    parser.add_argument("--mesh-dir", type=Path, help="also write both meshes here")
    parser.add_argument(
        "--colour-shift",
        type=int,
        default=0,
        help="shift colour images this many pixels right of the depth (a depth-colour "
        "calibration error, the first cause of colour bleed named in paper VI-B)",
    )
    args = parser.parse_args()

    sequence = open_dataset(args.scenario, progress=True)
    groundtruth = sequence.groundtruth_for_frames()
    truth = pyvista.read(sequence.path / "scene.ply")
    if "rgb" not in truth.point_data:  # PLY colours come back as "RGB"
        truth.point_data["rgb"] = truth.point_data["RGB"]
    config = Config(volume=VolumeConfig(resolution=args.resolution, size=args.size))
    settings = {
        "artifact_reduction": ColourConfig(),
        "plain": ColourConfig(angle_weighting=False, discontinuity_check=False),
    }
    first = groundtruth.poses[0]
    volumes = {name: tsdf.make_volume(config.volume, first) for name in settings}

    samples = mesh.sample_surface(truth, 0.01)
    volume = next(iter(volumes.values()))
    inside = np.all(
        (samples > volume.origin) & (samples < volume.origin + volume.size - volume.voxel_size),
        axis=1,
    )
    samples = samples[inside]
    seen = np.zeros(len(samples), dtype=bool)

    count = min(args.frames, len(sequence))
    started = time.perf_counter()
    for frame in tqdm(sequence.frames(0, count), total=count, unit="frame"):
        pose = groundtruth.poses[frame.index]
        if args.colour_shift:
            frame.colour = np.roll(frame.colour, args.colour_shift, axis=1)
        current = preprocess.preprocess_frame(
            frame.colour, frame.depth, sequence.camera, config.preprocess
        )
        for name, colour_config in settings.items():
            weights = colour.colour_weights(current, colour_config)
            tsdf.integrate(
                volumes[name], current.depth, pose, sequence.camera, current.colour, weights
            )
        seen |= mesh.visible_from(samples, [current.depth], [pose], sequence.camera)
    elapsed = time.perf_counter() - started

    results = {
        "scenario": args.scenario,
        "frames": count,
        "resolution": args.resolution,
        "size_m": args.size,
        "colour_shift_px": args.colour_shift,
        "seconds_per_frame_two_volumes": elapsed / count,
    }
    for name, fused in volumes.items():
        surface = mesh.extract_mesh(fused)
        results[name] = mesh.surface_accuracy(surface, truth, samples[seen]).as_dict()
        if args.mesh_dir:
            mesh.write_ply(args.mesh_dir / f"{args.scenario}_{name}.ply", surface)
            mesh.render_preview(
                surface, args.mesh_dir / f"{args.scenario}_{name}.png", view_pose=first
            )
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(results, indent=2) + "\n")
    print(json.dumps(results, indent=2))


if __name__ == "__main__":
    main()
