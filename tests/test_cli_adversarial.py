"""What a user can do to the command line that the other tests do not: a signal that lands
outside the frame loop (a warm-up, a benchmark), damaged images that a decoder would half read,
settings that no image can satisfy, and two commands into one output. Each test asserts the
exit status, the one line on stderr and what is left on disk. docs/reliability.md lists these
cases."""

import shutil
from pathlib import Path

import pytest

from kintinuous_ref.datasets import tum
from kintinuous_ref.program import cli, warmup
from kintinuous_ref.signals import Interrupted

TINY = Path(__file__).resolve().parent.parent / "data" / "tiny_desk"
SMALL = ["--backend", "ref", "--resolution", "32", "--volume-size", "2"]


def _errors(stderr: str) -> list[str]:
    """The command's own lines on stderr (progress bars left out)."""
    return [line for line in stderr.splitlines() if line.startswith("kintinuous:")]


def _signal_at(frame: int, name: str = "SIGTERM"):
    """A frame reader that raises the signal handler's Interrupted when it reaches `frame`, as
    the handler does in the main thread."""
    read = tum.TumSequence._read

    def reader(self, index: int):
        if index == frame:
            raise Interrupted(name)
        return read(self, index)

    return reader


def test_a_signal_during_the_warm_up_ends_the_command(monkeypatch, capsys):
    frames, camera, truth = warmup.warmup_frames()

    def interrupted_frames():
        def frames_then_signal():
            yield frames[0]
            raise Interrupted("SIGTERM")

        return frames_then_signal(), camera, truth

    monkeypatch.setattr(warmup, "warmup_frames", interrupted_frames)
    status = cli.main(["warmup", "--backend", "ref", "--odometry", "icp", "--serial"])
    captured = capsys.readouterr()
    assert status == 143
    assert _errors(captured.err) == ["kintinuous: interrupted by SIGTERM"]
    assert captured.out == ""  # no table of a warm-up that did not happen


def test_a_signal_during_a_benchmark_prints_no_timings(monkeypatch, capsys):
    monkeypatch.setattr(tum.TumSequence, "_read", _signal_at(3, "SIGINT"))
    argv = ["benchmark", str(TINY), "--frames", "6", "--odometry", "groundtruth", *SMALL]
    status = cli.main(argv)
    captured = capsys.readouterr()
    assert status == 130
    assert _errors(captured.err) == [
        "kintinuous: interrupted by SIGINT after 3 of 6 frames: no timings printed"
    ]
    assert captured.out == ""


@pytest.fixture
def copy(tmp_path) -> Path:
    """tiny_desk, copied to be damaged."""
    target = tmp_path / "seq"
    shutil.copytree(TINY, target)
    return target
