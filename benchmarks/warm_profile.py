"""Where a warm pipeline spends its time: cProfile over `kintinuous benchmark` after a first run
has compiled every kernel, so compilation stays out of the profile (the first run's time is
printed apart).

    python benchmarks/warm_profile.py DATASET --backend cuda --frames 30 [--set K=V] [--out F]

Prints the stages' medians, the functions with the most time of their own and the project's
functions by cumulative time, per frame; `--out` keeps the profile for pstats or snakeviz.
"""

from __future__ import annotations

import argparse
import cProfile
import json
import pstats
import time
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
    args = parser.parse_args()
    overrides = {key: json.loads(value) for key, _, value in (s.partition("=") for s in args.set)}
    config = with_overrides(Config(), overrides)
    run = dict(backend=args.backend, odometry=args.odometry, config=config)
    started = time.perf_counter()
    benchmark(args.dataset, frames=2, **run)
    print(f"first run (compiling or loading the kernels): {time.perf_counter() - started:.1f} s")
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


if __name__ == "__main__":
    main()
