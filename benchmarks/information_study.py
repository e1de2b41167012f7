"""What each term of the ICP+RGB-D cost knows, per scene: the eigenvalues of ICP's per-pair
information about the camera (odometry/combined.py `information_spectrum`), RGB-D's in the same
coordinates, and ICP's bias along its weakest direction.

For a few frame pairs of each sequence the TSDF is fused at the ground-truth poses (cpu backend),
the model raycast from the first pose, and both systems built at level 0 at the second frame's
true pose. There a perfect cost would ask for no step: the length of each cost's Gauss-Newton
step from the truth (translation, millimetres) measures its bias on that pair.

    python benchmarks/information_study.py corridor floor desk dark loop PATH/TO/redkitchen \\
        --size 320x240 --plot docs/odometry_information.png
"""

from __future__ import annotations

import argparse
from pathlib import Path

import cv2
import numpy as np

import kintinuous_fast
from kintinuous_ref.config import Config, VolumeConfig
from kintinuous_ref.odometry.combined import (
    DEGENERACY_THRESHOLD,
    information_spectrum,
    joint_system,
)
from kintinuous_ref.odometry.icp import IcpProblem
from kintinuous_ref.odometry.rgbd import RgbdProblem
from kintinuous_ref.odometry.solve import solve
from kintinuous_ref.preprocess import model_pyramid, preprocess_frame
from kintinuous_ref.program.reconstruct import open_dataset


def pair_systems(dataset: str, size: tuple[int, int], pairs: list[int], config: Config):
    """(icp, rgbd, camera position) at level 0 for each pair (k, k + 1), at the true poses."""
    sequence = open_dataset(dataset)
    truth = sequence.groundtruth_for_frames().poses
    camera = sequence.camera.resized(*size)
    fast = kintinuous_fast.load_backend("cpu")
    volume = fast.tsdf.make_volume(config.volume, truth[0])
    frames, models = [], {}
    for index, frame in enumerate(sequence.frames(0, max(pairs) + 2)):
        colour, depth = frame.colour, frame.depth
        if (colour.shape[1], colour.shape[0]) != size:
            colour = cv2.resize(colour, size, interpolation=cv2.INTER_AREA)
            depth = cv2.resize(depth, size, interpolation=cv2.INTER_NEAREST)
        frames.append(preprocess_frame(colour, depth, camera, config.preprocess))
        if index <= max(pairs):
            fast.tsdf.integrate(volume, frames[-1].depth, truth[index], camera)
        if index in pairs:
            model = fast.raycast.raycast(volume, truth[index], camera)
            models[index] = (model.vertices, model.normals)
    results = []
    for k in pairs:
        icp = IcpProblem(frames[k + 1].levels, model_pyramid(*models[k], 3), truth[k])
        rgbd = RgbdProblem(frames[k].levels, frames[k + 1].levels, truth[k])
        target = truth[k + 1]
        results.append((icp.system(0, target), rgbd.system(0, target), target[:3, 3]))
    return results


STEPS = ("icp", "rgbd", "paper", "degeneracy-aware", "information")


def truth_step_mm(icp, rgbd, centre, name: str) -> float:  # noqa: ANN001
    """Length (mm) of one Gauss-Newton step from the true pose: zero for an unbiased cost."""
    system = {"icp": icp, "rgbd": rgbd}.get(name)
    if system is None:
        system = joint_system(icp, rgbd, 1.0, name, camera_position=centre)
    step, _ = solve(system)
    return float("nan") if step is None else 1000 * float(np.linalg.norm(step[3:]))


def study(icp, rgbd, centre) -> dict[str, np.ndarray]:  # noqa: ANN001
    """ICP's eigenvalues, RGB-D's information along ICP's eigen-directions (same scaling, per
    pair) and each cost's step from the truth."""
    eigenvalues, eigenvectors, to_scaled = information_spectrum(icp, centre)
    rgbd_scaled = to_scaled.T @ rgbd.A @ to_scaled / max(rgbd.count, 1)
    rgbd_along = np.einsum("ij,ik,kj->j", eigenvectors, rgbd_scaled, eigenvectors)
    steps = np.array([truth_step_mm(icp, rgbd, centre, name) for name in STEPS])
    return {"icp": eigenvalues, "rgbd": rgbd_along, "steps": steps}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("datasets", nargs="+")
    parser.add_argument("--size", default="320x240")
    parser.add_argument("--pairs", default="30,90,150,210")
    parser.add_argument("--resolution", type=int, default=128)
    parser.add_argument("--volume-size", type=float, default=3.0)
    parser.add_argument("--plot", type=Path)
    args = parser.parse_args()
    size = tuple(int(n) for n in args.size.lower().split("x"))
    pairs = [int(k) for k in args.pairs.split(",")]
    config = Config(volume=VolumeConfig(resolution=args.resolution, size=args.volume_size))
    rows = {}
    for dataset in args.datasets:
        label = Path(dataset).name
        found = [study(*systems) for systems in pair_systems(dataset, size, pairs, config)]
        icp = np.median([f["icp"] for f in found], axis=0)
        rgbd = np.median([f["rgbd"] for f in found], axis=0)
        steps = np.nanmedian([f["steps"] for f in found], axis=0)
        rows[label] = (icp, rgbd, steps)
        print(f"{label:12s} ICP eigenvalues {np.array2string(icp, precision=4)}", flush=True)
        print(f"{'':12s} RGB-D along them {np.array2string(rgbd, precision=0)}")
        print(
            f"{'':12s} step from the truth (mm): "
            + ", ".join(f"{n} {v:.2f}" for n, v in zip(STEPS, steps, strict=True))
        )
    if args.plot:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        fig, ax = plt.subplots(figsize=(9, 3.6))
        x = np.arange(6)
        width = 0.8 / len(rows)
        for k, (label, (icp, _, _)) in enumerate(rows.items()):
            ax.bar(x + k * width, np.maximum(icp, 1e-7), width, label=label)
        threshold = DEGENERACY_THRESHOLD
        ax.axhline(threshold, color="k", ls="--", lw=1, label=f"degeneracy threshold {threshold}")
        ax.set_yscale("log")
        ax.set_xticks(x + 0.4 - width / 2, [f"#{i + 1}" for i in range(6)])
        ax.set_xlabel("ICP eigen-direction, weakest first")
        ax.set_ylabel("share of pairs observing it")
        ax.set_title(f"ICP's information per direction, {args.size} (median of pairs {args.pairs})")
        ax.legend(fontsize=7, ncol=2)
        fig.tight_layout()
        fig.savefig(args.plot, dpi=110)
        print(f"wrote {args.plot}")


if __name__ == "__main__":
    main()
