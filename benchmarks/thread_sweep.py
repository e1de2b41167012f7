"""How each stage and each parallel loop of the cpu pipeline scales with the thread count:
benchmarks/warm_profile.py --loops once per count, each in a child process started with
NUMBA_NUM_THREADS=N (numba fixes its thread count when it starts).

    python benchmarks/thread_sweep.py DATASET [--threads 1,2,4,8,16] [--frames 40]
        [--set K=V] [--json OUT]

Prints per stage the median ms per count and the speed-up against 1 thread (the smallest count
swept if 1 is not), per loop its ms per frame per count, its calls per frame and ms per call at
that baseline, and marks the loops that are slower at the largest count than at a smaller one,
most time lost first: these are the loops where waking and joining the other threads costs
more than the work they share. Below the stages, the machine's own ceilings at the same counts
(benchmarks/machine_scaling.py: a compute loop's speed-up and a memory triad's GB/s), so that a
stage whose speed-up follows the bandwidth rather than the cores shows as limited by memory.
Counts above the cores this process may run on are skipped, since threads that share a core
measure the scheduler, not the loops.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any

from kintinuous_ref.program.benchmark import machine_line

WARM_PROFILE = Path(__file__).resolve().with_name("warm_profile.py")
MACHINE_SCALING = Path(__file__).resolve().with_name("machine_scaling.py")


def parse_threads(text: str) -> list[int]:
    """The counts of a comma-separated list, ascending and without repeats."""
    counts = sorted({int(part) for part in text.split(",") if part.strip()})
    if not counts or counts[0] < 1:
        raise ValueError(f"thread counts must be positive integers, got {text!r}")
    return counts


def usable_cores() -> int:
    """The cores this process may run on (a container's or taskset's share, not the host's)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # no affinity on this platform
        return os.cpu_count() or 1


def split_counts(counts: list[int], cores: int) -> tuple[list[int], list[int]]:
    """(the counts to run, the counts above `cores` to skip)."""
    return [n for n in counts if n <= cores], [n for n in counts if n > cores]


def child_json(script: Path, arguments: list[str], threads: int) -> dict[str, Any]:
    """What `script` writes with --json, run in a child process with `threads` numba threads: a
    fresh process per count because numba reads NUMBA_NUM_THREADS once, when it starts."""
    environment = {**os.environ, "NUMBA_NUM_THREADS": str(threads)}
    with tempfile.TemporaryDirectory() as folder:
        out = Path(folder) / "report.json"
        command = [sys.executable, str(script), *arguments, "--json", str(out)]
        done = subprocess.run(command, env=environment, capture_output=True, text=True)
        if done.returncode != 0:
            raise RuntimeError(f"{' '.join(command)} failed:\n{done.stderr[-3000:]}")
        return json.loads(out.read_text())


def profile(dataset: str, threads: int, frames: int, options: list[str]) -> dict[str, Any]:
    """warm_profile.py's loop report on `threads` numba threads."""
    arguments = [dataset, "--loops", "--frames", str(frames), *options]
    return child_json(WARM_PROFILE, arguments, threads)


def machine_ceilings(counts: list[int]) -> dict[str, Any]:
    """machine_scaling.py's measurement at `counts`, its thread-count keys as integers again."""
    threads = ",".join(str(n) for n in counts)
    result = child_json(MACHINE_SCALING, ["--threads", threads], max(counts))
    result["rows"] = {int(n): row for n, row in result["rows"].items()}
    ups = result["speedups"]
    result["speedups"] = {kind: {int(n): v for n, v in ups[kind].items()} for kind in ups}
    return result


def baseline(counts: list[int]) -> int:
    """The count the speed-ups are against: 1 thread if swept, else the smallest."""
    return 1 if 1 in counts else min(counts)


def stage_rows(reports: dict[int, dict[str, Any]]) -> list[dict[str, Any]]:
    """Per stage (total last): its median ms per count, the speed-up against the baseline count
    and the time outside its loops per count, which tells the host's share from the loops'."""
    counts = sorted(reports)
    base = baseline(counts)
    stages = list(reports[base]["stage_medians_ms"])
    rows = []
    for stage in [s for s in stages if s != "total"] + ["total"]:
        ms = {n: reports[n]["stage_medians_ms"].get(stage) for n in counts}
        outside = {n: reports[n]["stages"].get(stage, {}).get("outside_ms") for n in counts}
        speedup = {n: ratio(ms[base], ms[n]) for n in counts}
        rows.append({"stage": stage, "ms": ms, "speedup": speedup, "outside_ms": outside})
    return rows


def ratio(numerator: float | None, denominator: float | None) -> float | None:
    """numerator / denominator, None where either is missing or the denominator is not positive."""
    if numerator is None or denominator is None or denominator <= 0:
        return None
    return numerator / denominator


def loop_rows(reports: dict[int, dict[str, Any]], noise_ms: float = 0.0) -> list[dict[str, Any]]:
    """Per loop: ms per frame per count (0 where a count never called it), calls per frame and
    ms per call at the baseline count, and the ms it loses at the largest count against the best
    smaller one (`slower` where above `noise_ms`, below which a timer cannot tell); sorted by
    that loss, largest first, so that the loops to fix lead."""
    counts = sorted(reports)
    base, largest = baseline(counts), counts[-1]
    names = {name for report in reports.values() for name in report["loops"]}
    rows = []
    for name in names:
        loops = {n: reports[n]["loops"].get(name) for n in counts}
        ms = {n: loop["ms_per_frame"] if loop else 0.0 for n, loop in loops.items()}
        calls = loops[base]["calls_per_frame"] if loops[base] else 0.0
        smaller = [ms[n] for n in counts if n < largest]
        lost = ms[largest] - min(smaller) if smaller else 0.0
        rows.append(
            {
                "loop": name,
                "ms": ms,
                "calls_per_frame": calls,
                "ms_per_call": ratio(ms[base], calls),
                "lost_ms": lost,
                "slower": lost > noise_ms,
            }
        )
    return sorted(rows, key=lambda row: (-row["lost_ms"], row["loop"]))


def cell(value: float | None, digits: int = 2) -> str:
    """A number of a table, '-' where there is none."""
    return "-" if value is None else f"{value:.{digits}f}"


def stage_table(rows: list[dict[str, Any]], counts: list[int]) -> list[str]:
    """The stage rows as text: ms, speed-up and time outside the loops per count."""
    base = baseline(counts)
    head = "".join(f"{n:>9d}" for n in counts)
    lines = [f"per stage: median ms, speed-up against {base} thread(s), ms outside the loops"]
    lines.append(f"{'stage':12s} {'':8s}{head}")
    for row in rows:
        for label, key, digits in (("ms", "ms", 2), ("speed-up", "speedup", 2)):
            values = "".join(f"{cell(row[key][n], digits):>9s}" for n in counts)
            lines.append(f"{row['stage'] if label == 'ms' else '':12s} {label:8s}{values}")
        if row["stage"] != "total":
            values = "".join(f"{cell(row['outside_ms'][n]):>9s}" for n in counts)
            lines.append(f"{'':12s} {'outside':8s}{values}")
    return lines


def fault_line(reports: dict[int, dict[str, Any]], counts: list[int]) -> str:
    """The minor page faults a frame per count (warm_profile's fault_summary): the median,
    and the first half's and second half's of the frames, '-' where a report has none."""
    cells = []
    for n in counts:
        faults = reports[n].get("minor_faults")
        keys = ("median", "first_half", "second_half")
        cells.append("/".join(f"{faults[key]:.0f}" for key in keys) if faults else "-")
    return "page faults a frame (median/first half/second half): " + ", ".join(
        f"{n}: {cell}" for n, cell in zip(counts, cells, strict=True)
    )


def ceiling_table(ceilings: dict[str, Any], counts: list[int]) -> list[str]:
    """The machine's speed-ups (machine_scaling.py) in the stage table's columns: what a stage
    limited by its cores, or by memory, would reach at each count."""
    base = baseline(counts)
    head = "".join(f"{n:>9d}" for n in counts)
    lines = [f"the machine's ceilings: speed-up against {base} thread(s) (machine_scaling.py)"]
    lines.append(f"{'':21s}{head}")
    for kind, label in (
        ("compute", "compute"),
        ("frame", "frame-sized triad"),
        ("volume", "volume-sized triad"),
    ):
        ups = ceilings["speedups"][kind]
        values = "".join(f"{cell(ratio(ups[n], ups[base])):>9s}" for n in counts)
        lines.append(f"{label:21s}{values}")
    return lines


def loop_table(rows: list[dict[str, Any]], counts: list[int]) -> list[str]:
    """The loop rows as text, '*' marking the loops slower at the largest count."""
    base, largest = baseline(counts), counts[-1]
    head = "".join(f"{n:>8d}" for n in counts)
    lines = [
        f"per loop: ms per frame per thread count; calls per frame and ms per call at {base} "
        "thread(s);",
        f"lost: ms at {largest} less the best smaller count (* slower at {largest} threads)",
        f"  {head}{'calls':>8s}{'ms/call':>9s}{'lost':>8s}  loop",
    ]
    for row in rows:
        values = "".join(f"{row['ms'][n]:8.2f}" for n in counts)
        mark = "*" if row["slower"] else " "
        lines.append(
            f"{mark} {values}{row['calls_per_frame']:8.1f}{cell(row['ms_per_call'], 3):>9s}"
            f"{row['lost_ms']:8.2f}  {row['loop']}"
        )
    return lines


def load_line() -> str:
    """The load average: on a shared machine the numbers mean little without it."""
    one, five, fifteen = os.getloadavg()
    return f"load average {one:.2f} {five:.2f} {fifteen:.2f}"


def machine() -> str:
    """machine_line's CPU model and count, without its numba thread count (this process's own
    default, not the children's) and with the cores usable here and the load average."""
    described = machine_line().split(", numba threads")[0]
    return f"{described}, {usable_cores()} usable, {load_line()}"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("dataset", help="TUM folder or synthetic scenario name")
    parser.add_argument("--threads", default="1,2,4,8,16", help="comma-separated counts")
    parser.add_argument("--frames", type=int, default=40)
    parser.add_argument("--odometry", default="icp+rgbd")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    parser.add_argument("--noise-ms", type=float, default=0.01, help="smallest loss marked")
    parser.add_argument("--json", type=Path, help="write the reports and the tables here")
    args = parser.parse_args()
    counts, skipped = split_counts(parse_threads(args.threads), usable_cores())
    if skipped:
        print(f"skipped {skipped}: more threads than the {usable_cores()} usable cores")
    if not counts:
        parser.error("no thread count fits this machine")
    options = ["--odometry", args.odometry] + [f"--set={item}" for item in args.set]
    start = machine()
    reports = {}
    for asked in counts:
        report = profile(args.dataset, asked, args.frames, options)
        if report["threads"] != asked:
            print(f"asked for {asked} threads, numba ran {report['threads']}")
        print(f"{report['threads']} thread(s) done, {load_line()}", flush=True)
        reports[report["threads"]] = report
    used = sorted(reports)
    ceilings = machine_ceilings(used)
    stages, loops = stage_rows(reports), loop_rows(reports, args.noise_ms)
    after = machine()
    if args.json:  # first: a reader that stops early (| head) must not lose it
        sweep = {"machine": [start, after], "threads": used, "skipped": skipped}
        sweep |= {
            "reports": reports,
            "stages": stages,
            "loops": loops,
            "machine_ceilings": ceilings,
        }
        args.json.write_text(json.dumps(sweep, indent=1) + "\n")
    timed = {report["timed_frames"] for report in reports.values()}
    print(f"\n{args.dataset}, threads {used}, medians over {sorted(timed)} timed frames\n")
    print("\n".join(stage_table(stages, used)))
    print(fault_line(reports, used) + "\n")
    print("\n".join(ceiling_table(ceilings, used)) + "\n")
    print("\n".join(loop_table(loops, used)) + "\n")
    print(f"before: {start}\nafter:  {after}")


if __name__ == "__main__":
    main()
