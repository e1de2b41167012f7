"""`kintinuous benchmark --json`: one JSON object whose per-stage statistics are those
of the frames after the warm-up frame, and frames/s = 1000 / median total ms, with the device
traffic per frame (zeros on the cpu; the cuda counts: tests/test_cuda_frame_budget.py)."""

import json
from pathlib import Path

import numpy as np
import pytest

from kintinuous_ref.program.cli import main

TINY_DESK = Path(__file__).resolve().parents[1] / "data" / "tiny_desk"


@pytest.mark.parametrize("fast", [False, True])
def test_benchmark_json_reports_stages_and_fps(capsys, fast):
    arguments = ["benchmark", str(TINY_DESK), "--backend", "cpu", "--frames", "3"]
    arguments += ["--resolution", "32", "--volume-size", "2", "--json"]
    main(arguments + (["--fast-odometry"] if fast else []))
    report = json.loads(capsys.readouterr().out)
    assert report["backend"] == "cpu" and report["odometry"] == "icp+rgbd"
    assert (report["frames"], report["timed_frames"]) == (3, 2)
    assert report["image"] == [160, 120] and report["resolution"] == 32
    assert report["icp_iterations"] == ([0, 5, 4] if fast else [10, 5, 4])
    stages = report["timing_ms"]
    assert {"preprocess", "odometry", "integrate", "raycast", "total"} <= set(stages)
    for stats in stages.values():  # two timed frames: median = mean, both <= max
        assert stats["median"] == pytest.approx(stats["mean"])
        assert 0 <= stats["mean"] <= stats["max"]
    parts = sum(stages[s]["mean"] for s in stages if s != "total")
    assert parts <= stages["total"]["mean"] * (1 + 1e-9)
    assert report["fps"] == pytest.approx(1000.0 / stages["total"]["median"])
    assert np.isfinite(report["fps"])
    # the device counters are there for every backend: zeros where nothing runs on a device
    for name in ("launches", "host_waits", "bytes_to_host", "graph_replays"):
        assert report[f"{name}_per_frame"] == 0
        assert {stats[name] for stats in report["traffic_per_stage"].values()} == {0}
    assert set(report["traffic_per_stage"]) == set(stages)


def test_benchmark_takes_configuration_overrides(capsys):
    # --set reaches the benchmarked configuration (as for reconstruct), after --resolution
    arguments = ["benchmark", str(TINY_DESK), "--backend", "cpu", "--frames", "2", "--json"]
    arguments += ["--resolution", "32", "--set", "icp.iterations=[3,2,1]"]
    main(arguments + ["--set", "volume.moving=false"])
    report = json.loads(capsys.readouterr().out)
    assert report["icp_iterations"] == [3, 2, 1]
    assert report["resolution"] == 32


class _DeviceWork:
    """The reference backend with a device whose queued work takes `seconds` to finish: what
    synchronize waits for."""

    def __init__(self, seconds: float) -> None:
        from kintinuous_ref.backend import ReferenceBackend

        self.inner, self.seconds, self.waits = ReferenceBackend(), seconds, 0

    def __getattr__(self, name: str):  # noqa: ANN204
        return getattr(self.inner, name)

    def synchronize(self) -> None:
        import time

        self.waits += 1
        time.sleep(self.seconds)


def test_synchronized_stages_include_their_device_work():
    from kintinuous_ref import pipeline
    from kintinuous_ref.config import Config, VolumeConfig
    from kintinuous_ref.program.reconstruct import open_dataset

    sequence = open_dataset(str(TINY_DESK))
    config = Config(volume=VolumeConfig(resolution=16, size=2.0, moving=False))
    runs = {}
    for synchronized in (False, True):
        backend = _DeviceWork(0.2)
        runs[synchronized] = (
            pipeline.run(
                sequence.frames(0, 2),
                sequence.camera,
                config,
                "icp",
                sequence.groundtruth_for_frames(),
                backend=backend,
                synchronize_stages=synchronized,
            ),
            backend.waits,
        )
    (plain, plain_waits), (synced, synced_waits) = runs[False], runs[True]
    assert plain_waits == 0
    stages = [stage for stage in synced.timings_ms if stage != "total"]
    assert {"preprocess", "odometry", "integrate", "raycast"} <= set(stages)
    assert synced_waits == sum(len(synced.timings_ms[stage]) for stage in stages)
    for stage in stages:  # each lap waited for the device's 200 ms
        assert min(synced.timings_ms[stage]) >= 200.0, (stage, synced.timings_ms[stage])
    assert min(plain.timings_ms["integrate"]) < 200.0  # a 16^3 volume: the ref's own time
