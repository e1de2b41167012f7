"""How fast the synthetic scenes render and write.

    .venv/bin/python benchmarks/synth_speed.py                 # render times, all scenarios
    .venv/bin/python benchmarks/synth_speed.py --write 300     # + write 300 desk frames, 640x480

Render: milliseconds per frame (wall and this process's CPU) at 160x120, 320x240, 640x480, with
the sensor model on, averaged over frames spread along a 300-frame sequence. Write: the whole
`write_scenario` (PNG files, scene.ply) with 1 and 2 worker processes.
"""

from __future__ import annotations

import argparse
import tempfile
import time

from kintinuous_ref.datasets import synthetic

SIZES = ((160, 120), (320, 240), (640, 480))


def render_times(name: str, width: int, height: int, repeats: int) -> tuple[float, float, float]:
    """(make_scenario ms, render wall ms, render CPU ms) per frame."""
    start = time.perf_counter()
    scenario = synthetic.make_scenario(name, frames=300, width=width, height=height)
    make_ms = (time.perf_counter() - start) * 1e3
    scenario.render(0)  # warm caches (noise tile)
    indices = [int(i) for i in range(0, 300, max(1, 300 // repeats))][:repeats]
    wall, cpu = time.perf_counter(), time.process_time()
    for index in indices:
        scenario.render(index)
    count = len(indices)
    return (
        make_ms,
        (time.perf_counter() - wall) * 1e3 / count,
        (time.process_time() - cpu) * 1e3 / count,
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=10)
    parser.add_argument("--write", type=int, default=0, help="also write this many desk frames")
    args = parser.parse_args()
    print(f"{'scenario':10s} {'size':>8s} {'make ms':>8s} {'wall ms':>8s} {'cpu ms':>8s}")
    for name in synthetic.list_scenarios():
        for width, height in SIZES:
            make_ms, wall_ms, cpu_ms = render_times(name, width, height, args.repeats)
            size = f"{width}x{height}"
            print(f"{name:10s} {size:>8s} {make_ms:8.1f} {wall_ms:8.1f} {cpu_ms:8.1f}")
    if args.write:
        for workers in (1, 2):
            with tempfile.TemporaryDirectory() as folder:
                start = time.perf_counter()
                synthetic.write_scenario("desk", folder, frames=args.write, workers=workers)
                seconds = time.perf_counter() - start
            print(f"write desk {args.write} frames 640x480, {workers} worker(s): {seconds:.1f} s")


if __name__ == "__main__":
    main()
