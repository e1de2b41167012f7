"""The depth noise weights on the ICP pairs (odometry/icp.py `pair_weights`), in one picture.

Left: the weight a pair keeps at each depth, relative to a pair at 1 m, for the model noise of
each image size (the voxel of the volume / sqrt(12)) and for the camera's axial noise alone.
Right: the position error frame by frame (after the ATE's rigid alignment) of the whole pipeline
on one scene (cpu backend, moving volume), for `rgbd` alone, `icp+rgbd` with every ICP pair alike
(`icp.depth_noise = false`, the previous default) and `icp+rgbd` with the weights (the default).

    python benchmarks/depth_noise_study.py corridor --plot docs/odometry_depth_noise.png
"""

from __future__ import annotations

import argparse
import tempfile
from dataclasses import replace
from pathlib import Path

import numpy as np

from kintinuous_ref import metrics
from kintinuous_ref.config import Config, VolumeConfig
from kintinuous_ref.datasets import tum
from kintinuous_ref.odometry.icp import depth_noise_scale, voxel_noise
from kintinuous_ref.program.evaluation.runs import RunSpec, run_one
from kintinuous_ref.program.reconstruct import open_dataset

# (label, method, icp.depth_noise)
RUNS = (
    ("rgbd alone", "rgbd", True),
    ("icp+rgbd, every ICP pair alike", "icp+rgbd", False),
    ("icp+rgbd, depth noise weights (default)", "icp+rgbd", True),
)
# The volumes of docs/odometry.md's setup: 3 m at 256^3 (640x480) and at 128^3 (320x240).
MODEL_NOISES = {"11.7 mm voxels (640x480)": 3.0 / 256, "23.4 mm voxels (320x240)": 3.0 / 128}


def position_errors(dataset: str, size: tuple[int, int], config: Config, frames: int) -> dict:
    """{label: (frame indices, position error in metres)} for each of RUNS."""
    path = str(open_dataset(dataset).path)
    truth = tum.open_sequence(path).groundtruth_for_frames()
    errors = {}
    with tempfile.TemporaryDirectory() as scratch:
        for index, (label, method, depth_noise) in enumerate(RUNS):
            run_config = replace(config, icp=replace(config.icp, depth_noise=depth_noise))
            out = f"{scratch}/{index}"
            spec = RunSpec(dataset, path, method, out, run_config, frames=frames, size=size,
                           backend="cpu")  # fmt: skip
            outcome = run_one(spec)
            if outcome.errors is None:
                raise SystemExit(f"{label}: {outcome.reason}")
            estimate = tum.read_trajectory(Path(out) / "trajectory.txt")
            count = len(estimate.positions)
            same_frames = tum.Trajectory(truth.timestamps[:count], truth.poses[:count])
            errors[label] = metrics.absolute_trajectory_errors(estimate, same_frames)
            rmse = 1000 * np.sqrt(np.mean(errors[label] ** 2))
            print(f"{label:42s} ATE {rmse:6.2f} mm", flush=True)
    return errors


def plot(errors: dict, title: str, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    depths = np.linspace(0.4, 4.0, 200)
    figure, (left, right) = plt.subplots(1, 2, figsize=(11, 4))
    for label, voxel in MODEL_NOISES.items():
        left.plot(depths, depth_noise_scale(depths, voxel_noise(voxel)) ** 2, label=label)
    left.plot(depths, depth_noise_scale(depths, 0.0) ** 2, "--", label="axial noise alone")
    left.set(xlabel="depth of the pair (m)", ylabel="weight relative to a pair at 1 m",
             yscale="log", title="a pair's weight: its information")  # fmt: skip
    left.legend(fontsize=8)
    for label, error in errors.items():
        rmse = 1000 * np.sqrt(np.mean(error**2))
        right.plot(1000 * error, label=f"{label}: ATE {rmse:.1f} mm")
    right.set(xlabel="frame", ylabel="position error (mm)", title=title)
    right.legend(fontsize=8)
    figure.tight_layout()
    figure.savefig(path, dpi=110)
    print(f"wrote {path}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("dataset", help="a scenario name or a TUM folder")
    parser.add_argument("--size", default="640x480", help="WIDTHxHEIGHT (images are resized)")
    parser.add_argument("--frames", type=int, default=300)
    parser.add_argument("--resolution", type=int, default=256)
    parser.add_argument("--volume-size", type=float, default=3.0)
    parser.add_argument("--plot", type=Path, required=True, help="the PNG to write")
    args = parser.parse_args()
    width, height = (int(n) for n in args.size.lower().split("x"))
    config = Config(volume=VolumeConfig(resolution=args.resolution, size=args.volume_size))
    errors = position_errors(args.dataset, (width, height), config, args.frames)
    title = f"{Path(args.dataset).name} at {args.size}, {args.frames} frames"
    plot(errors, title, args.plot)


if __name__ == "__main__":
    main()
