"""benchmarks/loop_anatomy.py: its clock is Python's monotonic clock, the loop calls it keeps are
replayed on the same arguments (the replay writes what the reference computes), and a traced
call's parts add up: one thread neither waits to wake nor idles, and busy time fits in the
call."""

import time

import benchmark_scripts
import numba
import numpy as np

from kintinuous_fast.odometry.icp import cpu as cpu_icp
from kintinuous_fast.odometry.sums import cpu as cpu_sums
from kintinuous_fast.targets import cpu as targets_cpu
from kintinuous_ref.odometry.icp import valid_points

loop_anatomy = benchmark_scripts.load("loop_anatomy")


def test_the_threads_clock_is_pythons_monotonic_clock():
    buffer = np.empty(2, dtype=np.int64)
    loop_anatomy.now_ns(buffer)  # compiled before the bracket
    before = time.monotonic_ns()
    inside = loop_anatomy.now_ns(buffer)
    after = time.monotonic_ns()
    assert before <= inside <= after


def maps(seed=3, shape=(30, 40)):
    """Vertex and normal maps with a quarter of their pixels invalid (NaN)."""
    rng = np.random.default_rng(seed)
    vertices = rng.normal(size=(*shape, 3)).astype(np.float32)
    normals = rng.normal(size=(*shape, 3)).astype(np.float32)
    vertices[rng.random(shape) < 0.25] = np.nan
    return vertices, normals


def test_a_kept_call_replays_the_loop_on_its_own_arguments():
    vertices, normals = maps()
    original = targets_cpu.run_parallel
    with loop_anatomy.Capture() as capture:
        assert cpu_sums.run_parallel is not original
        points = cpu_icp._valid_points(vertices, normals)
    assert cpu_sums.run_parallel is original and targets_cpu.run_parallel is original
    assert {"odometry._valid_counts", "odometry._compact_loop"} <= set(capture.calls)
    loop, args, parts, resets = capture.calls["odometry._compact_loop"]
    args[-1][:] = 0.0  # the compacted columns, written again by the replay
    threads = numba.get_num_threads()
    timed = loop_anatomy.timed_call(loop, args, parts, threads, resets)
    expected = np.concatenate(valid_points(vertices, normals))
    np.testing.assert_array_equal(args[-1], expected.astype(np.float32))
    np.testing.assert_array_equal(points, args[-1])
    assert timed["busy"] <= threads * timed["call"]


def test_one_thread_neither_waits_to_wake_nor_idles():
    vertices, normals = maps(seed=4)
    with loop_anatomy.Capture() as capture:
        cpu_icp._valid_points(vertices, normals)
    loop, args, parts, resets = capture.calls["odometry._valid_counts"]
    timed = loop_anatomy.timed_call(loop, args, parts, 1, resets)
    assert timed["wake"] == 0.0 and timed["imbalance"] == 0.0
    assert 0.0 < timed["busy"] <= timed["call"]
    assert timed["join"] >= 0.0


def test_the_table_lists_the_most_time_lost_first():
    row = dict.fromkeys(loop_anatomy.COLUMNS, 1.0)
    rows = {"a": {**row, "lost_us": 5.0}, "b": {**row, "lost_us": 50.0}, "c": row}
    lines = loop_anatomy.table(rows, 4, top=2)
    assert "on 4 threads" in lines[0]
    assert [line.split()[-1] for line in lines[2:]] == ["b", "a"]
    assert lines[2].split()[2] == "50.0"
