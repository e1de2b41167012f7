"""What the host pays per frame to find a segment's CUDA graph (kintinuous_fast/targets/
cuda_graphs.py): building the key of a frame's recorded launches and looking it up as `flush`
does (in, get, move to the end), with stand-ins for numba's device arrays, no GPU needed.

    python benchmarks/graph_key_cost.py [--launches 130] [--arguments 12] [--repeats 200]

The defaults are a frame of the pipeline at 640x480 (about 130 launches, 1 600 arguments, most
of them device arrays). Prints the median microseconds of each, and per argument.
"""

from __future__ import annotations

import argparse
import time
from collections import OrderedDict
from collections.abc import Callable
from types import SimpleNamespace

import numpy as np

from kintinuous_fast.targets import cuda_graphs


class StandInArray:
    """What a key reads of a numba device array: its address, shape, strides and type."""

    def __init__(self, address: int) -> None:
        self.device_ctypes_pointer = SimpleNamespace(value=address)
        self.shape, self.strides, self.dtype = (480, 640), (5120, 8), np.dtype(float)

    def copy_to_host(self) -> None: ...


def frame_launches(launches: int, arguments: int) -> list[cuda_graphs.Launch]:
    """`launches` launches of `arguments` each: three in four device arrays (40 distinct, as
    a frame's buffers repeat across kernels), then a float, an int and a tuple of two."""
    arrays = [StandInArray(4096 * (k + 1)) for k in range(40)]
    arrays_each = arguments - 3
    return [
        cuda_graphs.Launch(
            print,
            (300, 1),
            (128, 1),
            0,
            (*(arrays[(i + k) % 40] for k in range(arrays_each)), 0.5, i, (1.0, 2.0)),
        )
        for i in range(launches)
    ]


def median_us(function: Callable[[], object], repeats: int) -> float:
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        function()
        times.append(time.perf_counter() - start)
    return float(np.median(times) * 1e6)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--launches", type=int, default=130)
    parser.add_argument("--arguments", type=int, default=12)
    parser.add_argument("--repeats", type=int, default=200)
    args = parser.parse_args()
    cuda_graphs._simulated = lambda: False  # the stand-ins have a GPU array's address
    launches = frame_launches(args.launches, args.arguments)
    graphs = OrderedDict({cuda_graphs._key(launches): "graph"})

    def look_up() -> None:
        key = cuda_graphs._key(launches)
        if key in graphs:
            graphs.move_to_end(key)
            graphs[key]

    key_us = median_us(lambda: cuda_graphs._key(launches), args.repeats)
    lookup_us = median_us(look_up, args.repeats)
    count = args.launches * args.arguments
    print(f"{args.launches} launches, {count} arguments")
    print(f"key: {key_us:.0f} us ({key_us / count:.2f} us an argument)")
    print(f"key and lookups: {lookup_us:.0f} us ({lookup_us / count:.2f} us an argument)")


if __name__ == "__main__":
    main()
