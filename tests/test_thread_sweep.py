"""benchmarks/thread_sweep.py's tables from two made-up loop reports (1 and 4 threads): the
stages' speed-ups against 1 thread, the loops slower at 4 threads marked and sorted by the time
they lose, the counts above the cores skipped."""

import benchmark_scripts
import pytest

thread_sweep = benchmark_scripts.load("thread_sweep")
warm_profile = benchmark_scripts.load("warm_profile")


def report(threads, medians, loops, outside):
    """A warm_profile.py --loops --json report: loops as {name: (ms per frame, calls)}."""
    return {
        "threads": threads,
        "timed_frames": 39,
        "stage_medians_ms": medians,
        "loops": {
            name: {"ms_per_frame": ms, "calls_per_frame": calls}
            for name, (ms, calls) in loops.items()
        },
        "stages": {stage: {"outside_ms": ms} for stage, ms in outside.items()},
    }


REPORTS = {
    1: report(
        1,
        {"preprocess": 12.0, "odometry": 40.0, "total": 52.0},
        {
            "preprocess._bilateral_rows": (8.0, 1),
            "odometry._icp_loop": (20.0, 16),
            "odometry._valid_counts": (0.3, 3),
        },
        {"preprocess": 4.0, "odometry": 19.7},
    ),
    4: report(
        4,
        {"preprocess": 6.0, "odometry": 50.0, "total": 56.0},
        {
            "preprocess._bilateral_rows": (2.0, 1),
            "odometry._icp_loop": (26.0, 16),
            "odometry._valid_counts": (0.9, 3),
        },
        {"preprocess": 4.0, "odometry": 23.1},
    ),
}


def test_stage_rows_give_the_speed_up_against_one_thread():
    rows = {row["stage"]: row for row in thread_sweep.stage_rows(REPORTS)}
    assert list(rows) == ["preprocess", "odometry", "total"]
    assert rows["preprocess"]["ms"] == {1: 12.0, 4: 6.0}
    assert rows["preprocess"]["speedup"] == {1: 1.0, 4: 2.0}
    assert rows["odometry"]["speedup"][4] == pytest.approx(0.8)
    assert rows["total"]["speedup"][4] == pytest.approx(52 / 56)
    assert rows["odometry"]["outside_ms"] == {1: 19.7, 4: 23.1}
    assert rows["total"]["outside_ms"] == {1: None, 4: None}  # no stage of its own


def test_loop_rows_mark_the_loops_slower_at_the_largest_count_by_time_lost():
    rows = thread_sweep.loop_rows(REPORTS)
    assert [row["loop"] for row in rows] == [
        "odometry._icp_loop",
        "odometry._valid_counts",
        "preprocess._bilateral_rows",
    ]
    icp, counts, bilateral = rows
    assert icp["lost_ms"] == pytest.approx(6.0) and icp["slower"]
    assert counts["lost_ms"] == pytest.approx(0.6) and counts["slower"]
    assert bilateral["lost_ms"] == pytest.approx(-6.0) and not bilateral["slower"]
    assert icp["calls_per_frame"] == 16 and icp["ms_per_call"] == pytest.approx(1.25)
    assert counts["ms_per_call"] == pytest.approx(0.1)
    assert icp["ms"] == {1: 20.0, 4: 26.0}
    # a loss within the timer's noise is not marked
    assert not thread_sweep.loop_rows(REPORTS, noise_ms=0.7)[1]["slower"]


def test_the_best_smaller_count_is_the_reference_for_the_loss():
    middle = report(
        2,
        {"preprocess": 7.0, "odometry": 30.0, "total": 37.0},
        {"odometry._icp_loop": (14.0, 16)},
        {},
    )
    rows = {row["loop"]: row for row in thread_sweep.loop_rows({**REPORTS, 2: middle})}
    assert rows["odometry._icp_loop"]["lost_ms"] == pytest.approx(26.0 - 14.0)
    # a loop a count never called counts 0 ms there, the best smaller count
    assert rows["odometry._valid_counts"]["ms"][2] == 0.0
    assert rows["odometry._valid_counts"]["lost_ms"] == pytest.approx(0.9)


def test_without_one_thread_the_smallest_count_is_the_baseline():
    rows = thread_sweep.stage_rows({4: REPORTS[4], 8: {**REPORTS[4], "threads": 8}})
    assert rows[0]["speedup"] == {4: 1.0, 8: 1.0}


def test_counts_are_parsed_sorted_and_those_above_the_cores_skipped():
    assert thread_sweep.parse_threads("16,1,2,2") == [1, 2, 16]
    assert thread_sweep.split_counts([1, 2, 4, 8, 16], 4) == ([1, 2, 4], [8, 16])
    with pytest.raises(ValueError):
        thread_sweep.parse_threads("0,2")


def test_the_tables_print_every_count_and_the_marks():
    counts = sorted(REPORTS)
    stages = thread_sweep.stage_table(thread_sweep.stage_rows(REPORTS), counts)
    assert "speed-up against 1 thread(s)" in stages[0]
    assert stages[-1].split()[-2:] == ["1.00", "0.93"]  # total's speed-up
    loops = thread_sweep.loop_table(thread_sweep.loop_rows(REPORTS), counts)
    marked = [line.split()[-1] for line in loops if line.startswith("*")]
    assert marked == ["odometry._icp_loop", "odometry._valid_counts"]


def test_the_machine_ceilings_print_against_the_same_baseline():
    # machine_scaling.py's speed-ups against its first count, 2 here: the table rebases them
    # on the sweep's own baseline, 4 threads in a sweep of 4 and 8
    ceilings = {
        "speedups": {
            "compute": {2: 1.0, 4: 1.9, 8: 3.8},
            "frame": {2: 1.0, 4: 1.6, 8: 2.4},
            "volume": {2: 1.0, 4: 1.2, 8: 1.2},
        }
    }
    lines = thread_sweep.ceiling_table(ceilings, [4, 8])
    assert "against 4 thread(s)" in lines[0]
    values = {line[:21].strip(): line.split()[-2:] for line in lines[2:]}
    assert values == {
        "compute": ["1.00", "2.00"],
        "frame-sized triad": ["1.00", "1.50"],
        "volume-sized triad": ["1.00", "1.00"],
    }


def test_each_frame_counts_the_faults_of_its_own_work(monkeypatch):
    """LoopClock.frames: a frame's faults are those taken from when the pipeline gets it until
    it asks for the next (here the work of frame k takes 10 k faults, reading one takes 1)."""
    taken = [0]
    monkeypatch.setattr(warm_profile, "minor_faults", lambda: taken[0])
    clock = warm_profile.LoopClock()

    def read():
        for index in range(4):
            taken[0] += 1  # reading a frame: not its work
            yield index

    for index in clock.frames(read()):
        taken[0] += 10 * index
    assert clock.faults == [[0, 10, 20, 30]]


def test_the_fault_summary_splits_the_growing_frames_from_the_steady_ones():
    summary = warm_profile.fault_summary([100, 90, 10, 0, 2, 4])
    assert summary == {"median": 7.0, "first_half": 90.0, "second_half": 2.0}
    assert warm_profile.fault_summary([5]) == {"median": 5.0, "first_half": 5.0, "second_half": 5.0}
    assert warm_profile.fault_summary([]) is None
    reports = {1: {"minor_faults": summary}, 4: {}}
    line = thread_sweep.fault_line(reports, [1, 4])
    assert line.endswith("1: 7/90/2, 4: -")
