"""A real recording that comes back to where it started: a TUM folder played forward on its even
frames, then backward on its odd frames, written as a new TUM folder (docs/loop_closure.md).

    python benchmarks/there_and_back.py DATA/redkitchen OUT [--frames N]

The camera retraces its path to its first pose, so loop closure has real places to recognise,
and the way back never shows an image the way out showed: each frame of it lies between two
frames of the way out, with its own sensor noise. OUT holds the images as lossless PNG, new
timestamps 1/15 s apart (every other frame of a 30 Hz recording) and the recording's ground
truth, frame by frame. An easier revisit
than a new path through the same room: the viewpoints on the way back are those of the way out.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from kintinuous_ref.datasets import tum
from kintinuous_ref.errors import DatasetError

STEP = 2.0 / 30.0  # seconds between the frames written: every other frame of 30 Hz


def there_and_back(count: int) -> list[int]:
    """Indices of a `count`-frame recording: the even ones forward, then the odd ones back."""
    forward = list(range(0, count, 2))
    back = [index for index in range(count - 1, 0, -1) if index % 2 == 1]
    return forward + back


def write_folder(source: Path, out: Path, frames: int | None) -> int:
    """Write OUT as described above; the number of frames written."""
    sequence = tum.open_sequence(source)
    if sequence.groundtruth is None:
        raise DatasetError(f"{source}: no groundtruth.txt, so no error could be measured")
    truth = sequence.groundtruth_for_frames()
    order = there_and_back(min(frames or len(sequence), len(sequence)))
    stamps = 1.0 + STEP * np.arange(len(order))
    replayed = (
        tum.Frame(position, float(stamps[position]), frame.colour, frame.depth)
        for position, frame in ((position, sequence[index]) for position, index in enumerate(order))
    )
    return tum.write_sequence(
        out, replayed, sequence.camera, tum.Trajectory(stamps, truth.poses[order])
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("source", type=Path, help="a TUM folder with groundtruth.txt")
    parser.add_argument("out", type=Path)
    parser.add_argument("--frames", type=int, help="use the first N frames of the recording")
    args = parser.parse_args()
    written = write_folder(args.source, args.out, args.frames)
    print(f"wrote {written} frames to {args.out}")


if __name__ == "__main__":
    main()
