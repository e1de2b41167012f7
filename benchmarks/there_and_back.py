"""A real recording that comes back to where it started: a TUM folder played forward on every
`stride`-th frame from the first, then backward on the frames halfway between those, written as
a new TUM folder (docs/loop_closure.md).

    python benchmarks/there_and_back.py DATA/redkitchen OUT [--frames N] [--stride S]

The camera retraces its path to its first pose, so loop closure has real places to recognise,
and the way back never shows an image the way out showed: each frame of it lies between two
frames of the way out, with its own sensor noise. OUT holds the images as lossless PNG, new
timestamps `stride`/30 s apart (every `stride`-th frame of a 30 Hz recording: 2, the default,
keeps the recording's speed at half its frame rate; more makes the camera move further between
frames, so the tracker drifts more) and the recording's ground truth, frame by frame. An easier
revisit than a new path through the same room: the viewpoints on the way back are those of the
way out.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from kintinuous_ref.datasets import tum
from kintinuous_ref.errors import DatasetError

RATE = 30.0  # frames per second of the recordings this is for (7-Scenes, TUM)


def there_and_back(count: int, stride: int = 2) -> list[int]:
    """Indices of a `count`-frame recording: every `stride`-th from 0 forward, then those
    stride // 2 after each of them back (stride 2: the even frames forward, the odd back)."""
    forward = list(range(0, count, stride))
    back = [index + stride // 2 for index in forward if index + stride // 2 < count]
    return forward + back[::-1]


def write_folder(source: Path, out: Path, frames: int | None, stride: int = 2) -> int:
    """Write OUT as described above; the number of frames written."""
    if stride < 2:
        raise DatasetError(
            f"--stride must be at least 2 (the way back needs frames between), got {stride}"
        )
    sequence = tum.open_sequence(source)
    if sequence.groundtruth is None:
        raise DatasetError(f"{source}: no groundtruth.txt, so no error could be measured")
    truth = sequence.groundtruth_for_frames()
    order = there_and_back(min(frames or len(sequence), len(sequence)), stride)
    stamps = 1.0 + stride / RATE * np.arange(len(order))
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
    parser.add_argument("--stride", type=int, default=2, help="frames apart on the way out")
    args = parser.parse_args()
    try:
        written = write_folder(args.source, args.out, args.frames, args.stride)
    except DatasetError as error:
        parser.exit(2, f"there_and_back: {error}\n")
    print(f"wrote {written} frames to {args.out}")


if __name__ == "__main__":
    main()
