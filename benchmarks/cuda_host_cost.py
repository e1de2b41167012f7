"""The host's share of a cuda frame, measured without a GPU: the Python that a replayed frame
still runs (the stages' own code, recording launches, keys, pooled buffers, the record's
reading), which on a GPU lies on the frame's critical path (docs/benchmarks.md).

    python benchmarks/cuda_host_cost.py [--frames 40] [--warmup 8] [--profile N]

The cuda backend runs the pipeline in numba's simulator with graphs on (the tests' quicker
scheduling, tests/quick_simulator.py): the desk at 40x30, the default odometry (icp+rgbd,
10/5/4 iterations over three levels, so the frame launches what a 640x480 frame launches) and a
fixed 24^3 volume. The first `--warmup` frames run their kernels, which makes every stage's
buffers and graphs (a stage's pooled buffers settle into their cycle within the first six or
so frames); after them every kernel and replay is skipped (the buffers keep the last
real frame's values, so each stage still takes the same branches) and the signed segments are
not checked, as on a GPU. What is timed is then only the host: the stages' medians in
milliseconds, the launches and graph replays per frame, the launches the host's Python still
records and the arguments it keys, and with `--profile N` the N functions with the most time of
their own. Driver calls (graph launches, the pinned copies, the one wait) are not in it: on a
GPU they add tens of microseconds.
"""

from __future__ import annotations

import argparse
import cProfile
import os
import pstats
import sys
import time
from pathlib import Path

os.environ["NUMBA_ENABLE_CUDASIM"] = "1"
os.environ["KINTINUOUS_CUDA_GRAPHS"] = "1"
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

import numpy as np  # noqa: E402
from quick_simulator import install  # noqa: E402

install()

from kintinuous_fast import load_backend  # noqa: E402
from kintinuous_fast.targets import cuda_graphs  # noqa: E402
from kintinuous_ref import pipeline  # noqa: E402
from kintinuous_ref.config import Config, TrackingConfig, VolumeConfig  # noqa: E402
from kintinuous_ref.datasets.synthetic import make_scenario  # noqa: E402
from kintinuous_ref.datasets.tum import Frame  # noqa: E402

SIZE = (40, 30)  # width, height: the launches do not depend on it, the simulator's time does
CONFIG = Config(
    volume=VolumeConfig(resolution=24, size=4.0, moving=False),
    tracking=TrackingConfig(min_correspondences=10),  # few points per level at 80x60
)


def count_recorded(counts: list[int]) -> None:
    """Count each launch that the host's Python records (counts[0]) and each argument that a
    segment's key reads (counts[1]): what a replayed frame still pays per launch."""
    record, key = cuda_graphs.record, cuda_graphs._key

    def counted_record(dispatcher: object, configuration: object, arguments: tuple) -> None:
        counts[0] += 1
        record(dispatcher, configuration, arguments)

    def counted_key(launches: list) -> object:
        counts[1] += sum(len(getattr(launch, "arguments", ())) for launch in launches)
        return key(launches)

    cuda_graphs.record, cuda_graphs._key = counted_record, counted_key


def skip_kernels_after(
    warmup: int, frames: list[Frame], profile: cProfile.Profile | None, recorded: list[int]
):
    """The frames, with every kernel launch and replay skipped from frame `warmup` on (uploads
    still copy) and the profile, if any, running over those frames only."""
    launch_each = cuda_graphs._launch_each
    skipping = False

    def uploads_only(launches: list) -> None:
        if skipping:
            launches = [launch for launch in launches if isinstance(launch, cuda_graphs.Upload)]
        launch_each(launches)

    cuda_graphs._launch_each = uploads_only
    for index, frame in enumerate(frames):
        if index == warmup:
            skipping = True
            cuda_graphs.RECORDER.verify = False  # as on a GPU: signed segments replay alone
            count_recorded(recorded)
            if profile is not None:
                profile.enable()
        yield frame
    if profile is not None:
        profile.disable()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=40, help="frames timed")
    parser.add_argument("--warmup", type=int, default=8, help="frames whose kernels run")
    parser.add_argument("--profile", type=int, default=0, metavar="N", help="list N functions")
    args = parser.parse_args()
    count = args.warmup + args.frames
    desk = make_scenario("desk", frames=count, width=SIZE[0], height=SIZE[1])
    frames = [
        Frame(index, float(desk.trajectory.timestamps[index]), *desk.render(index))
        for index in range(count)
    ]
    profile = cProfile.Profile() if args.profile else None
    recorded = [0, 0]
    started = time.perf_counter()
    result = pipeline.run(
        skip_kernels_after(args.warmup, frames, profile, recorded),
        desk.camera,
        CONFIG,
        "icp+rgbd",
        backend=load_backend("cuda"),
    )
    print(f"{count} frames in {time.perf_counter() - started:.0f} s, {args.warmup} with kernels")
    timed = slice(args.warmup, None)
    for stage, laps in result.timings_ms.items():
        print(f"{stage:>12} {np.median(laps[timed]):7.3f} ms (host, median)")
    traffic = result.traffic["total"][timed]
    print(f"launches per frame {np.median([t.launches for t in traffic]):.0f}, "
          f"graph replays {np.median([t.graph_replays for t in traffic]):.0f}, "
          f"tracking failures {result.tracking_failures}")  # fmt: skip
    print(f"per frame, the host's Python recorded {recorded[0] / args.frames:.0f} launches "
          f"and keyed {recorded[1] / args.frames:.0f} of their arguments")  # fmt: skip
    if profile is not None:
        stats = pstats.Stats(profile)
        stats.sort_stats("tottime").print_stats(args.profile)
        stats.sort_stats("cumulative").print_stats(args.profile)


if __name__ == "__main__":
    main()
