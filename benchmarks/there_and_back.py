"""A real recording that comes back to where it started: a TUM folder played forward on every
`stride`-th frame from the first, then backward on the frames halfway between those, written as
a new TUM folder (docs/loop_closure.md).

    python benchmarks/there_and_back.py DATA/redkitchen OUT [--frames N] [--stride S] [--start F]

The camera retraces its path to its first pose, so loop closure has real places to recognise,
and the way back never shows an image the way out showed: each frame of it lies between two
frames of the way out, with its own sensor noise. OUT holds the images as lossless PNG, new
timestamps `stride`/30 s apart (every `stride`-th frame of a 30 Hz recording: 2, the default,
keeps the recording's speed at half its frame rate; more makes the camera move further between
frames, so the tracker drifts more) and the recording's ground truth, frame by frame. An easier
revisit than a new path through the same room: the viewpoints on the way back are those of the
way out. With `--start F` the way out begins at frame F and the way back goes on to frame 0: its
last stretch shows the start of the way out from where the camera was F frames earlier (an offset
return; pick F from the ground truth so that those views are far enough apart).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import cv2
import numpy as np

from kintinuous_ref.datasets import tum
from kintinuous_ref.errors import DatasetError
from kintinuous_ref.loop_closure.calibration import there_and_back_order

RATE = 30.0  # frames per second of the recordings this is for (7-Scenes, TUM)


def there_and_back(count: int, stride: int = 2, start: int = 0) -> list[int]:
    """Indices of a `count`-frame recording: every `stride`-th from `start` forward, then those
    stride // 2 after every `stride`-th from 0 back to the first (stride 2, start 0: the even
    frames forward, the odd back). A `start` past 0 offsets the return: the way back goes on
    past where the way out began, to frames it never showed."""
    order = there_and_back_order(count, stride)
    forward = [index for index in order[: len(range(0, count, stride))] if index >= start]
    return forward + order[len(range(0, count, stride)) :]


def scaled(frame: tum.Frame, size: tuple[int, int] | None) -> tum.Frame:
    """The frame with its images scaled to `size` (width, height), or as it is."""
    if size is None or frame.colour.shape[1::-1] == size:
        return frame
    colour = cv2.resize(frame.colour, size, interpolation=cv2.INTER_AREA)
    depth = cv2.resize(frame.depth, size, interpolation=cv2.INTER_NEAREST)  # no mixed depths
    return tum.Frame(frame.index, frame.timestamp, colour, depth)


def write_folder(  # noqa: PLR0913
    source: Path,
    out: Path,
    frames: int | None,
    stride: int = 2,
    start: int = 0,
    size: tuple[int, int] | None = None,
) -> int:
    """Write OUT as described above, its images scaled to `size` (width, height) if given; the
    number of frames written."""
    if stride < 2:
        raise DatasetError(
            f"--stride must be at least 2 (the way back needs frames between), got {stride}"
        )
    sequence = tum.open_sequence(source)
    if sequence.groundtruth is None:
        raise DatasetError(f"{source}: no groundtruth.txt, so no error could be measured")
    truth = sequence.groundtruth_for_frames()
    order = there_and_back(min(frames or len(sequence), len(sequence)), stride, start)
    stamps = 1.0 + stride / RATE * np.arange(len(order))
    replayed = (
        scaled(tum.Frame(position, float(stamps[position]), frame.colour, frame.depth), size)
        for position, frame in ((position, sequence[index]) for position, index in enumerate(order))
    )
    camera = sequence.camera if size is None else sequence.camera.resized(*size)
    return tum.write_sequence(out, replayed, camera, tum.Trajectory(stamps, truth.poses[order]))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("source", type=Path, help="a TUM folder with groundtruth.txt")
    parser.add_argument("out", type=Path)
    parser.add_argument("--frames", type=int, help="use the first N frames of the recording")
    parser.add_argument("--stride", type=int, default=2, help="frames apart on the way out")
    parser.add_argument("--width", type=int, help="scale the images to this width (4:3)")
    parser.add_argument(
        "--start", type=int, default=0, help="the way out begins at this frame (an offset return)"
    )
    args = parser.parse_args()
    try:
        size = (args.width, args.width * 3 // 4) if args.width else None
        written = write_folder(args.source, args.out, args.frames, args.stride, args.start, size)
    except DatasetError as error:
        parser.exit(2, f"there_and_back: {error}\n")
    print(f"wrote {written} frames to {args.out}")


if __name__ == "__main__":
    main()
