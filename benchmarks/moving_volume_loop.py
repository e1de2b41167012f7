"""Score a moving-volume reconstruction (`kintinuous reconstruct ... --out RUN`) of a synthetic
sequence against its true surface (scene.ply in the dataset folder).

    .venv/bin/python benchmarks/moving_volume_loop.py DATASET RUN [--spacing 0.02]
        [--radius 0.02] [--every 5] [--out RUN/score.json]

"Seen along the path": true-surface samples (`--spacing` apart) that some camera saw (its depth
within 2 cm of the sample's, every `--every`th frame) while the sample lay inside that frame's
volume (volume_origins.txt of the run).
Completeness = share of those within `--radius` of the mesh; accuracy = mean distance of the
mesh's vertices to the true surface.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import pyvista
from tqdm import tqdm

from kintinuous_ref import mesh, moving_volume
from kintinuous_ref.datasets import tum


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("dataset", type=Path)
    parser.add_argument("run", type=Path)
    parser.add_argument("--spacing", type=float, default=0.02)
    parser.add_argument("--radius", type=float, default=0.02)
    parser.add_argument("--every", type=int, default=5)
    parser.add_argument("--out", type=Path)
    parser.add_argument("--preview", type=Path, help="also render the mesh from above here")
    args = parser.parse_args()

    report = json.loads((args.run / "report.json").read_text())
    sequence = tum.open_sequence(args.dataset)
    poses = tum.read_trajectory(args.run / "trajectory.txt").poses
    origins = np.loadtxt(args.run / "volume_origins.txt", ndmin=2)[:, 1:]
    n, voxel = report["volume"]["resolution"], report["volume"]["voxel_m"]

    truth = pyvista.read(args.dataset / "scene.ply")
    if "rgb" not in truth.point_data:
        truth.point_data["rgb"] = truth.point_data["RGB"]
    samples = mesh.sample_surface(truth, args.spacing)
    seen = np.zeros(len(samples), dtype=bool)
    camera = sequence.camera
    for index in tqdm(range(0, len(poses), args.every), desc="visibility"):
        lo, hi = origins[index], origins[index] + (n - 1) * voxel
        inside = np.all((samples >= lo) & (samples <= hi), axis=1) & ~seen
        if not inside.any():
            continue
        depth = sequence[index].depth
        candidates = np.flatnonzero(inside)
        visible = mesh.visible_from(samples[candidates], [depth], [poses[index]], camera)
        seen[candidates[visible]] = True

    reconstruction = moving_volume.read_mesh(args.run / "mesh.ply")
    if args.preview:
        # From above: looking down world -z (the synthetic scenes' up is +z), a little tilted.
        above = np.eye(4)
        above[:3, :3] = np.column_stack([[1.0, 0, 0], [0, -1.0, 0], [0, 0, -1.0]])
        mesh.render_preview(reconstruction, args.preview, view_pose=above, size=(1200, 900))
    score = mesh.surface_accuracy(reconstruction, truth, samples[seen], args.radius)
    result = {
        "run": str(args.run),
        "frames": len(poses),
        "samples": len(samples),
        "seen_samples": int(seen.sum()),
        **score.as_dict(),
    }
    print(json.dumps(result, indent=2))
    out = args.out or args.run / "score.json"
    out.write_text(json.dumps(result, indent=2) + "\n")


if __name__ == "__main__":
    main()
