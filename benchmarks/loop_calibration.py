"""Loop verification's statistics on real revisits whose truth is known (docs/loop_closure.md).

    python benchmarks/loop_calibration.py OUT [--width 640] [--strides 2 4 6] [--no-twins]

Builds candidates from redkitchen's frames 0-299 at their ground-truth poses
(kintinuous_ref/loop_closure/calibration.py): the candidates a run verifies when the recording is
played there and back at each stride; offset returns, each frame against the nearest earlier one
(at least 30 frames before) that is at least 15 cm and 15 degrees from it; pairs whose views
share no surface, most ORB matches first (these two kinds also with the dense alignment started
from the true relative pose 10 cm and 3 degrees off, as a tracked run's odometry starts it
where the sparse stage refuses); and the synthetic `twins` walk. For each it records
every check's statistic, the true overlap of the two views and how far the dense alignment
ended from the true relative pose, then writes OUT/loop_calibration.json (every candidate, the
settings, a summary per kind, and the effective pairs of a loop's alignment that
`loop_closure.loop_effective_pairs` is set from: calibration.effective_pairs) and
OUT/loop_calibration.png (each statistic, right against wrong candidates, with the thresholds).
Skips with a message where redkitchen is absent.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
from pathlib import Path

import numpy as np

from kintinuous_ref.config import LoopClosureConfig
from kintinuous_ref.datasets import data_folder, real_dataset, tum
from kintinuous_ref.loop_closure import calibration

OFFSET_METRES, OFFSET_DEGREES = 0.15, 15.0  # an offset return's views at least this far apart
OFFSET_GAP, OFFSET_STEP = 30, 10  # frames between an offset pair at least; frames tried
APART_FRAMES, APART_PAIRS = 20, 12  # every 20th frame for pairs without overlap; how many
# The drift of an odometry start (metres, degrees): the tracked offset loops on redkitchen began
# up to 11 cm and 3.4 degrees from the ground truth's relative pose
ODOMETRY_DRIFT = (0.1, 3.0)


def all_candidates(
    width: int, strides: list[int], twins: bool, settings: LoopClosureConfig
) -> list[calibration.Candidate]:
    sequence = tum.open_sequence(real_dataset("redkitchen"))
    truth = sequence.groundtruth_for_frames().poses
    make = calibration.KeyframeMaker(sequence, truth, width, width * 3 // 4, settings)
    rng = np.random.default_rng(0)
    started = time.perf_counter()
    candidates = []
    for stride in strides:
        candidates += calibration.there_and_back_candidates(make, stride, settings, rng)
        print(
            f"stride {stride}: {len(candidates)} candidates, {time.perf_counter() - started:.0f} s"
        )
    pairs = calibration.offset_pairs(truth, OFFSET_METRES, OFFSET_DEGREES, OFFSET_GAP, OFFSET_STEP)
    candidates += calibration.measure_pairs("offset return", make, pairs, settings, rng)
    candidates += calibration.measure_pairs(
        "offset return, from odometry", make, pairs, settings, rng, ODOMETRY_DRIFT
    )
    print(f"offset: {len(candidates)} candidates, {time.perf_counter() - started:.0f} s")
    frames = list(range(0, len(truth), APART_FRAMES))
    pairs = calibration.apart_pairs(make, frames, APART_PAIRS, settings)
    candidates += calibration.measure_pairs("views apart", make, pairs, settings, rng)
    candidates += calibration.measure_pairs(
        "views apart, from odometry", make, pairs, settings, rng, ODOMETRY_DRIFT
    )
    if twins:
        candidates += calibration.twins_candidates(settings, rng)
    print(f"all: {len(candidates)} candidates, {time.perf_counter() - started:.0f} s")
    return candidates


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("out", type=Path)
    parser.add_argument("--width", type=int, default=640, help="frames scaled to this width")
    parser.add_argument("--strides", type=int, nargs="+", default=[2, 4, 6])
    parser.add_argument("--no-twins", action="store_true", help="leave out the synthetic walk")
    args = parser.parse_args()
    if real_dataset("redkitchen") is None:
        parser.exit(0, f"redkitchen not found in {data_folder()}: nothing to calibrate on\n")
    settings = LoopClosureConfig()
    candidates = all_candidates(args.width, args.strides, not args.no_twins, settings)
    args.out.mkdir(parents=True, exist_ok=True)
    summary = calibration.summary(candidates)
    pairs = calibration.effective_pairs(candidates)
    result = {
        "width": args.width,
        "effective_pairs": pairs,
        "settings": dataclasses.asdict(settings),
        "summary": summary,
        "candidates": [c.as_dict() for c in candidates],
    }
    (args.out / "loop_calibration.json").write_text(json.dumps(result, indent=1) + "\n")
    figure = calibration.draw_distributions(candidates, settings)
    figure.savefig(args.out / "loop_calibration.png", dpi=110)
    print(json.dumps(summary, indent=1))
    print(f"effective pairs of a loop's alignment (right candidates): {pairs:.2f}")


if __name__ == "__main__":
    main()
