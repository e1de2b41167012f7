"""A bit-for-bit snapshot of what a backend computes, to check that a refactoring changes nothing.

    python benchmarks/regression_snapshot.py save BEFORE.npz [--dataset redkitchen] [--frames 40]
    python benchmarks/regression_snapshot.py compare BEFORE.npz

Runs the pipeline over the first frames of a dataset (default: the shared redkitchen frames)
with each odometry method that exercises a different path of the kernels (ICP, RGB-D, the joint
system, FOVIS switching), with the moving volume on (the default), and stores every pose and
the final volume's arrays. `compare` runs the same again and reports, per array, whether it is
identical to the stored one bit for bit (and the largest difference where not); it exits 1 on
any difference.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from kintinuous_ref import pipeline
from kintinuous_ref.backend import load_backend
from kintinuous_ref.config import Config
from kintinuous_ref.datasets import real_dataset
from kintinuous_ref.program.reconstruct import open_dataset

METHODS = ("icp", "rgbd", "icp+rgbd", "fovis/icp+rgbd")


def snapshot(dataset: str, frames: int, backend: str) -> dict[str, np.ndarray]:
    """Every pose and volume array of one run per method, keyed 'method/what'."""
    chosen = load_backend(backend)
    sequence = open_dataset(dataset, frames_needed=frames)
    groundtruth = sequence.groundtruth_for_frames() if sequence.groundtruth is not None else None
    arrays: dict[str, np.ndarray] = {}
    for method in METHODS:
        result = pipeline.run(
            sequence.frames(0, frames), sequence.camera, Config(), method, groundtruth,
            backend=chosen,
        )
        volume = chosen.host_volume(result.volume)
        arrays[f"{method}/poses"] = np.stack(result.poses)
        arrays[f"{method}/fused"] = np.array(result.fused)
        for name in ("tsdf", "weight", "colour", "colour_weight", "offset", "origin"):
            arrays[f"{method}/{name}"] = np.asarray(getattr(volume, name))
        print(f"{method}: {result.frames} frames, {result.tracking_failures} failures", flush=True)
    return arrays


def compare(stored: dict[str, np.ndarray], now: dict[str, np.ndarray]) -> bool:
    same = True
    for key in sorted(stored):
        before, after = stored[key], now.get(key)
        if after is not None and before.shape == after.shape and np.array_equal(
            before.view(np.uint8), np.ascontiguousarray(after).view(np.uint8)
        ):
            continue
        same = False
        if after is None or before.shape != after.shape:
            print(f"DIFFERENT {key}: shape {before.shape} against "
                  f"{None if after is None else after.shape}")
        else:
            gap = np.nanmax(np.abs(before.astype(np.float64) - after.astype(np.float64)))
            print(f"DIFFERENT {key}: largest difference {gap:.3g}")
    print("bit-identical" if same else "differences found")
    return same


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("action", choices=("save", "compare"))
    parser.add_argument("file", type=Path)
    parser.add_argument("--dataset", default=None, help="default: the shared redkitchen frames")
    parser.add_argument("--frames", type=int, default=40)
    parser.add_argument("--backend", default="cpu")
    args = parser.parse_args()
    dataset = args.dataset
    if dataset is None:
        folder = real_dataset("redkitchen")
        if folder is None:
            sys.exit("the redkitchen frames are not here (see docs/datasets.md); give --dataset")
        dataset = str(folder)
    arrays = snapshot(dataset, args.frames, args.backend)
    if args.action == "save":
        np.savez_compressed(args.file, **arrays)
        print(f"saved {len(arrays)} arrays to {args.file}")
        return
    with np.load(args.file) as stored:
        same = compare(dict(stored), arrays)
    sys.exit(0 if same else 1)


if __name__ == "__main__":
    main()
