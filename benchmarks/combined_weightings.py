"""The ICP+RGB-D weightings side by side: ATE RMSE of the whole pipeline (cpu backend, moving
volume, first pose from the ground truth) for `icp`, `rgbd` and `icp+rgbd` under every
`combined.weighting`, on synthetic scenarios and TUM folders.

    python benchmarks/combined_weightings.py corridor floor --size 320x240 --resolution 128
    python benchmarks/combined_weightings.py desk PATH/TO/redkitchen --size 640x480 --json out.json

Prints one row per run as it finishes and a markdown table at the end (docs/odometry.md).
"""

from __future__ import annotations

import argparse
import json
import tempfile
from dataclasses import replace
from pathlib import Path

from kintinuous_ref.config import Config, VolumeConfig, with_overrides
from kintinuous_ref.odometry.combined import WEIGHTINGS
from kintinuous_ref.odometry.icp import ROBUST_KERNELS
from kintinuous_ref.program.evaluation.runs import RunSpec, run_one
from kintinuous_ref.program.reconstruct import open_dataset


def runs(args: argparse.Namespace) -> list[tuple[str, str]]:
    """(method label, weighting or '') in table order: the methods, `icp` under each robust
    kernel of --icp-kernels, then `icp+rgbd` under each weighting."""
    rows = [(method, "") for method in args.methods]
    rows += [(f"icp {kernel}", "") for kernel in args.icp_kernels]
    return rows + [(f"icp+rgbd {weighting}", weighting) for weighting in args.weightings]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("datasets", nargs="+", help="scenario names or TUM folders")
    parser.add_argument("--size", default="320x240", help="WIDTHxHEIGHT (images are resized)")
    parser.add_argument("--frames", type=int, default=300)
    parser.add_argument("--resolution", type=int, default=128)
    parser.add_argument("--volume-size", type=float, default=3.0)
    parser.add_argument("--methods", nargs="*", default=["icp", "rgbd"])
    parser.add_argument("--weightings", nargs="*", default=list(WEIGHTINGS))
    parser.add_argument(
        "--icp-kernels",
        nargs="*",
        default=[],
        choices=[kernel for kernel in ROBUST_KERNELS if kernel != "none"],
        help="also run `icp` alone with each of these icp.robust_kernel values",
    )
    parser.add_argument("--backend", default="cpu", help="ref, cpu or cuda (default: cpu)")
    parser.add_argument("--json", type=Path, help="also write the results here")
    parser.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="a configuration value for every run (JSON value), repeatable",
    )
    args = parser.parse_args()
    width, height = (int(n) for n in args.size.lower().split("x"))
    base = Config(volume=VolumeConfig(resolution=args.resolution, size=args.volume_size))
    base = with_overrides(
        base, {k: json.loads(v) for k, _, v in (s.partition("=") for s in args.set)}
    )
    results: dict[str, dict[str, dict]] = {}
    with tempfile.TemporaryDirectory() as scratch:
        for dataset in args.datasets:
            path = str(open_dataset(dataset).path)
            label = Path(dataset).name
            for name, weighting in runs(args):
                method, _, variant = name.partition(" ")
                config = base
                if method == "icp" and variant:
                    config = replace(base, icp=replace(base.icp, robust_kernel=variant))
                if weighting:
                    config = replace(base, combined=replace(base.combined, weighting=weighting))
                spec = RunSpec(
                    label,
                    path,
                    method,
                    f"{scratch}/{label}-{len(results)}",
                    config,
                    frames=args.frames,
                    size=(width, height),
                    backend=args.backend,
                )
                outcome = run_one(spec)
                ate = outcome.errors["ate_rmse"] * 1000 if outcome.errors else None
                row = {
                    "ate_mm": ate,
                    "failures": outcome.tracking_failures,
                    "status": outcome.status,
                    "reason": outcome.reason,
                    "s": outcome.seconds,
                }
                results.setdefault(label, {})[name] = row
                shown = f"{ate:8.1f} mm" if ate is not None else f"FAILED {outcome.reason}"
                print(
                    f"{label:12s} {name:28s} {shown}  {outcome.tracking_failures} failed "
                    f"({outcome.seconds:.0f} s)",
                    flush=True,
                )
            if args.json:
                args.json.write_text(json.dumps(results, indent=1))
    labels = list(results)
    print(f"\n| method ({args.size}, {args.frames} frames) | " + " | ".join(labels) + " |")
    print("|---" * (len(labels) + 1) + "|")
    for name, _ in runs(args):
        cells = []
        for label in labels:
            row = results[label][name]
            cell = "-" if row["ate_mm"] is None else f"{row['ate_mm']:.1f} mm"
            cells.append(cell + (f" ({row['failures']} failed)" if row["failures"] else ""))
        print(f"| `{name}` | " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main()
