"""How many Jacobi sweeps the discount's eigenproblem takes on real frames, from the identity
and from the last Gauss-Newton step's eigenvectors (the solve kernel's warm start,
odometry/frame_solve.py): counted, so no GPU is needed and the machine's speed cannot move it.

    python benchmarks/warm_start_sweeps.py DATA/redkitchen [--frames 60] [--every 3]

The reference tracker (icp+rgbd, the defaults) runs on every `--every`-th of the first
`--frames` frames at 160x120 and each step's information matrix (the one
`combined.information_spectrum` decomposes) is kept. Each is then solved by the team's
eigensolver (solve/ops.py, run as plain Python on one lane) from the identity, and from the
eigenvectors the step before it left, the basis reset to the identity at each frame's start as
the device does (sweeps counted by jacobi_sweeps.py).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
from jacobi_sweeps import sweeps_taken
from there_and_back import scaled

from kintinuous_ref import pipeline
from kintinuous_ref.config import Config
from kintinuous_ref.datasets import tum
from kintinuous_ref.odometry import combined

SIZE = (160, 120)


def recorded_informations(data: Path, frames: int, every: int) -> list[np.ndarray | None]:
    """Each step's information matrix in order, None where a frame begins."""
    sequence = tum.open_sequence(data)
    chosen = [scaled(sequence[index], SIZE) for index in range(0, frames, every)]
    kept: list[np.ndarray | None] = []
    decompose = np.linalg.eigh

    class Recording:  # the module's np.linalg, its eigh keeping what it is given
        def __getattr__(self, name: str) -> object:
            return getattr(np.linalg, name)

        @staticmethod
        def eigh(matrix: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
            kept.append(np.array(matrix))
            return decompose(matrix)

    class NumpyRecording:
        linalg = Recording()

        def __getattr__(self, name: str) -> object:
            return getattr(np, name)

    real_numpy, combined.np = combined.np, NumpyRecording()
    try:
        pipeline.run(
            chosen, sequence.camera.resized(*SIZE), Config(), "icp+rgbd",
            progress=lambda _result: kept.append(None),
        )  # fmt: skip
    finally:
        combined.np = real_numpy
    return kept


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("data", type=Path, help="a TUM-format folder (redkitchen)")
    parser.add_argument("--frames", type=int, default=60)
    parser.add_argument("--every", type=int, default=3)
    args = parser.parse_args()
    cold, warm = [], []
    basis = np.eye(6)
    for matrix in recorded_informations(args.data, args.frames, args.every):
        if matrix is None:  # a new frame: the device resets its basis
            basis = np.eye(6)
            continue
        cold.append(sweeps_taken(matrix)[0])
        sweeps, basis = sweeps_taken(matrix, basis)
        warm.append(sweeps)
    print(f"{len(cold)} eigenproblems, sweeps per eigenproblem (mean, max, count of each):")
    for name, counts in (("from the identity", cold), ("warm start", warm)):
        print(f"  {name:18} {np.mean(counts):.2f}  {max(counts)}  {np.bincount(counts).tolist()}")


if __name__ == "__main__":
    main()
