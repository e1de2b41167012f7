"""Frames read ahead on a thread (kintinuous_ref.program.read_ahead): the items come in index
order and equal reading in turn, on another thread, at most the stated depth ahead of the
caller; an error reaches the caller at its own index, reading going on after the kind the
caller skips and stopping after any other; closing early stops the thread. A reconstruction
read by three threads equals one read by one, a corrupt frame skipped and counted in both."""

import json
import shutil
import threading
from pathlib import Path

import pytest

from kintinuous_ref.errors import DatasetError
from kintinuous_ref.program.read_ahead import ReadAhead, readers_for


class Source:
    """read(i) = i * i, recording the indices read and the threads that read them."""

    def __init__(self, bad: dict[int, BaseException] | None = None) -> None:
        self.read_indices: list[int] = []
        self.threads: set[int] = set()
        self.bad = bad or {}
        self.reached: dict[int, threading.Event] = {}

    def read(self, index: int) -> int:
        self.read_indices.append(index)
        self.threads.add(threading.get_ident())
        self.reached.setdefault(index, threading.Event()).set()
        if index in self.bad:
            raise self.bad[index]
        return index * index

    def wait_for(self, index: int) -> bool:
        return self.reached.setdefault(index, threading.Event()).wait(timeout=10.0)


def test_items_come_in_order_read_on_another_thread():
    source = Source()
    with ReadAhead(source.read, range(3, 40)) as items:
        got = list(items)
    assert got == [(i, i * i, None) for i in range(3, 40)]
    assert source.threads and threading.get_ident() not in source.threads


@pytest.mark.parametrize("readers", [2, 3, 7])
def test_several_readers_hand_out_every_index_once_in_order(readers):
    source = Source()
    with ReadAhead(source.read, range(5, 36), readers=readers) as items:
        got = list(items)
    assert got == [(i, i * i, None) for i in range(5, 36)]
    assert len(source.threads) >= 2  # reading did spread (each thread reads its share)


def test_one_reader_per_four_cores_up_to_four():
    assert [readers_for(cores) for cores in (1, 2, 4, 7, 8, 16, 64)] == [1, 1, 1, 1, 2, 4, 4]


def test_an_error_is_the_last_item_with_several_readers():
    error = OSError("disk gone")
    source = Source(bad={6: error})
    with ReadAhead(source.read, range(40), readers=3, goes_on_after=DatasetError) as items:
        got = list(items)
    assert got == [(i, i * i, None) for i in range(6)] + [(6, None, error)]


def test_reading_runs_ahead_of_the_caller_by_the_depth_and_no_further():
    source, depth = Source(), 3
    with ReadAhead(source.read, range(100), depth=depth) as reader:
        items = iter(reader)
        assert next(items) == (0, 0, None)
        # while the caller holds item 0, the thread fills the queue with 1..depth and reads
        # one more, which waits for room
        assert source.wait_for(depth + 1)
        assert max(source.read_indices) == depth + 1
        assert [next(items)[0] for _ in range(5)] == [1, 2, 3, 4, 5]


def test_a_skippable_error_comes_at_its_index_and_reading_goes_on():
    error = DatasetError("frame 4: corrupt")
    source = Source(bad={4: error})
    with ReadAhead(source.read, range(8), goes_on_after=DatasetError) as items:
        got = list(items)
    assert [index for index, _, _ in got] == list(range(8))
    assert got[4] == (4, None, error)
    assert all(failure is None for index, _, failure in got if index != 4)


def test_any_other_error_is_the_last_item():
    error = OSError("disk gone")
    source = Source(bad={2: error})
    with ReadAhead(source.read, range(50), goes_on_after=DatasetError) as items:
        got = list(items)
    assert got == [(0, 0, None), (1, 1, None), (2, None, error)]
    assert max(source.read_indices) == 2


@pytest.mark.parametrize("taken", [0, 1, 5])
def test_closing_early_stops_the_thread(taken):
    source, depth = Source(), 2
    reader = ReadAhead(source.read, range(1000), depth=depth)
    items = iter(reader)
    for _ in range(taken):
        next(items)
    reader.close()
    assert not reader.alive()
    assert max(source.read_indices, default=-1) <= taken + depth + 1


TINY = Path(__file__).resolve().parent.parent / "data" / "tiny_desk"


def _reconstruct(dataset: Path, out: Path, readers: int, monkeypatch) -> dict:
    """The tiny desk reconstructed on the reference (ground-truth poses, a 32^3 volume) with
    `readers` threads reading ahead; report.json."""
    from kintinuous_ref.config import Config, VolumeConfig
    from kintinuous_ref.program import reconstruct as program

    monkeypatch.setattr(program, "readers_for", lambda: readers)
    config = Config(volume=VolumeConfig(resolution=32, size=2.0))
    sequence = program.open_dataset(str(dataset))
    assert sequence.parallel_reads  # a TUM folder: each read opens its own files
    program.reconstruct(sequence, out, config, show_progress=False, skip_bad_frames=True)
    return json.loads((out / "report.json").read_text())


def test_a_run_read_by_three_threads_equals_one_read_by_one(tmp_path, monkeypatch):
    copy = tmp_path / "tiny"
    shutil.copytree(TINY, copy)
    corrupt = sorted((copy / "rgb").iterdir())[7]
    corrupt.write_bytes(b"not an image")
    reports = [
        _reconstruct(copy, tmp_path / f"out{readers}", readers, monkeypatch) for readers in (1, 3)
    ]
    for report in reports:  # the corrupt frame skipped and counted, the others fused in order
        assert report["frames"] == 9 and report["skipped_frames"] == 1, report
        assert report["skipped_reasons"][0].startswith(f"frame 7: {corrupt}")
    one, three = ((tmp_path / f"out{n}" / "trajectory.txt").read_text() for n in (1, 3))
    assert one == three
