"""What reading the frames costs a run, read in turn or ahead on a thread
(kintinuous_ref.program.read_ahead), for a frame of given host and wait times.

    python benchmarks/read_ahead.py TUM_FOLDER [--frames 60] [--host-ms 1.0] [--wait-ms 3.0]
        [--readers N]

A GPU frame is mostly the host waiting for the device (the interpreter lock released, as in a
CUDA synchronize) and a little of the host's Python; `--wait-ms` and `--host-ms` stand in for
them (a sleep, and a busy Python loop). The defaults are about a cuda frame at 640x480 with
the host's work replayed (docs/benchmarks.md). Prints the median milliseconds a frame takes
to read and decode alone, and the milliseconds a frame of the loop takes with the frames read
in turn and read ahead.
"""

from __future__ import annotations

import argparse
import contextlib
import time

import numpy as np

from kintinuous_ref.datasets.tum import FrameSequence
from kintinuous_ref.program.read_ahead import ReadAhead, readers_for
from kintinuous_ref.program.reconstruct import open_dataset


def stand_in_frame(host_ms: float, wait_ms: float) -> None:
    """`host_ms` of Python holding the interpreter lock, then `wait_ms` of waiting."""
    until = time.perf_counter() + host_ms / 1000.0
    while time.perf_counter() < until:
        pass
    time.sleep(wait_ms / 1000.0)


def loop_ms(sequence: FrameSequence, frames: int, readers: int, host_ms: float, wait_ms: float):
    """Milliseconds a frame of a loop over `frames` frames (median of its frames), the frames
    read ahead by `readers` threads (0: read in turn)."""
    indices = range(frames)
    with contextlib.ExitStack() as stack:
        if readers:
            items = stack.enter_context(ReadAhead(sequence.__getitem__, indices, readers=readers))
        else:
            items = (sequence[index] for index in indices)
        laps, last = [], time.perf_counter()
        for _ in items:
            stand_in_frame(host_ms, wait_ms)
            now = time.perf_counter()
            laps.append(now - last)
            last = now
    return 1000.0 * float(np.median(laps[1:]))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("dataset", help="TUM folder")
    parser.add_argument("--frames", type=int, default=60)
    parser.add_argument("--host-ms", type=float, default=1.0)
    parser.add_argument("--wait-ms", type=float, default=3.0)
    parser.add_argument("--readers", type=int, default=readers_for(), help="threads reading ahead")
    args = parser.parse_args()
    sequence = open_dataset(args.dataset, frames_needed=args.frames)
    started = time.perf_counter()
    for index in range(args.frames):
        sequence[index]
    read = 1000.0 * (time.perf_counter() - started) / args.frames
    work = args.host_ms + args.wait_ms
    print(f"reading and decoding alone: {read:.2f} ms a frame (mean); the frame itself {work} ms")
    for readers in (0, args.readers, 0, args.readers):
        name = f"{readers} reading ahead" if readers else "read in turn"
        took = loop_ms(sequence, args.frames, readers, args.host_ms, args.wait_ms)
        print(f"{name:>16}: {took:.2f} ms a frame ({1000.0 / took:.0f} frames/s)")


if __name__ == "__main__":
    main()
