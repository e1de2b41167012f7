"""Where a warm pipeline spends its time: cProfile over `kintinuous benchmark` after a first run
has compiled every kernel, so compilation stays out of the profile (the first run's time is
printed apart).

    python benchmarks/warm_profile.py DATASET --backend cuda --frames 30 [--set K=V] [--out F]
    python benchmarks/warm_profile.py DATASET --loops [--frames 30]

Prints the stages' medians, the functions with the most time of their own and the project's
functions by cumulative time, per frame; `--out` keeps the profile for pstats or snakeviz.
`--loops` (cpu backend) runs without the profiler and times every parallel loop instead: its
wall time per frame (the helper threads' hand-over included) and, per stage, the time outside
the loops, which is what the host's Python costs.
"""

from __future__ import annotations

import argparse
import cProfile
import json
import pstats
import sys
import time
from collections import defaultdict
from pathlib import Path

from kintinuous_ref.config import Config, with_overrides
from kintinuous_ref.program.benchmark import benchmark


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("dataset", help="TUM folder or synthetic scenario name")
    parser.add_argument("--backend", default="cpu")
    parser.add_argument("--odometry", default="icp+rgbd")
    parser.add_argument("--frames", type=int, default=30)
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    parser.add_argument("--top", type=int, default=25, help="rows of each listing")
    parser.add_argument("--out", type=Path, help="write the profile here")
    parser.add_argument("--loops", action="store_true", help="time each cpu loop, no profiler")
    args = parser.parse_args()
    overrides = {key: json.loads(value) for key, _, value in (s.partition("=") for s in args.set)}
    config = with_overrides(Config(), overrides)
    run = dict(backend=args.backend, odometry=args.odometry, config=config)
    started = time.perf_counter()
    benchmark(args.dataset, frames=2, **run)
    print(f"first run (compiling or loading the kernels): {time.perf_counter() - started:.1f} s")
    if args.loops:
        print_loop_times(args.dataset, args.frames, run)
        return
    profiler = cProfile.Profile()
    result = profiler.runcall(benchmark, args.dataset, frames=args.frames, **run)
    medians = {stage: round(t["median"], 2) for stage, t in result["timing_ms"].items()}
    print(f"medians (ms), frames 2..{args.frames}, profiled: {medians}")
    # The benchmark runs 2 frames to warm up, then `frames` timed ones.
    frames = args.frames + 2
    if args.out:
        profiler.dump_stats(args.out)
    stats = pstats.Stats(profiler)
    for order, restriction in (("tottime", ()), ("cumulative", ("kintinuous",))):
        print(f"\n{order}, ms per frame ({frames} frames), calls per frame:")
        stats.sort_stats(order)
        rows = [
            (key, stats.stats[key])
            for key in stats.fcn_list
            if all(word in key[0] for word in restriction)
        ][: args.top]
        for (file, line, name), (_, calls, own, cumulative, _) in rows:
            where = f"{Path(file).parent.name}/{Path(file).name}:{line}({name})"
            print(
                f"{1000 * own / frames:8.2f} {1000 * cumulative / frames:8.2f} "
                f"{calls / frames:8.1f}  {where}"
            )


def print_loop_times(dataset: str, frames: int, run: dict) -> None:
    """Run the benchmark with every kintinuous_fast module's run_parallel timed (the cpu loops
    are called through it) and print ms per frame per loop and per stage."""
    import kintinuous_fast.targets.cpu as threads

    untimed = threads.run_parallel
    seconds: dict[str, float] = defaultdict(float)
    calls: dict[str, int] = defaultdict(int)

    def timed(loop, *args, **options):  # noqa: ANN001, ANN002, ANN003, ANN202
        started = time.perf_counter()
        untimed(loop, *args, **options)
        name = f"{loop.__module__.split('.')[1]}.{loop.__name__}"
        seconds[name] += time.perf_counter() - started
        calls[name] += 1

    modules = [m for n, m in sys.modules.items() if n.startswith("kintinuous_fast.")]
    patched = [m for m in modules if getattr(m, "run_parallel", None) is untimed]
    for module in patched:
        module.run_parallel = timed
    try:
        result = benchmark(dataset, frames=frames, **run)
    finally:
        for module in patched:
            module.run_parallel = untimed
    count = frames + 2  # the benchmark's 2 warm-up frames, then the timed ones
    medians = {stage: t["median"] for stage, t in result["timing_ms"].items()}
    print(f"stage medians (ms), frames 2..{frames}: {medians}")
    print("\nms per frame (mean over every frame, the 2 warm-up frames included), calls per frame:")
    per_stage: dict[str, float] = defaultdict(float)
    for name in sorted(seconds, key=seconds.get, reverse=True):
        per_stage[name.split(".")[0]] += seconds[name]
        print(f"{1000 * seconds[name] / count:8.2f} {calls[name] / count:6.1f}  {name}")
    print("\nper stage package: loops, and the stage's median less its loops")
    stage_of = {"tsdf": "integrate", "colour": "integrate"}  # the others share their names
    outside = dict(medians)
    for package, total in per_stage.items():
        stage = stage_of.get(package, package)
        outside[stage] = outside.get(stage, 0.0) - 1000 * total / count
        print(f"{package:12s} loops {1000 * total / count:7.2f}")
    print({stage: round(ms, 2) for stage, ms in outside.items() if stage != "total"})
    loops = 1000 * sum(per_stage.values()) / count
    print(f"all loops {loops:.2f} ms of a median frame of {medians['total']:.2f} ms")


if __name__ == "__main__":
    main()
