"""The cpu backend's loops on several threads (kintinuous_fast.targets.cpu): every item of a
loop's range is done exactly once, in parts that follow the closed form, whatever the number of
threads and parts; each thread gets a work-array row of its own; an error on another thread
reaches the caller; a signal during a loop is raised once every part is done; a call runs on
no more threads than its work wants; and a forked child runs its loops too."""

import _thread
import multiprocessing
import os
import signal
import threading

import numba
import numpy as np
import pytest
from threads_child import run_with_threads

from kintinuous_fast.targets import cpu
from kintinuous_fast.targets.cpu import (
    LOOP_COSTS,
    NEXT_PART,
    PARTS_DONE,
    claim_slot,
    claimed_items,
    parallel_part,
    run_parallel,
    run_parallel_above,
    spin_below,
)

THREADS = sorted({1, min(2, numba.config.NUMBA_NUM_THREADS)})


@parallel_part()
def _count_items(claims, parts, seen, slots):
    """seen[i] += 1 and slots[i] = this thread's slot, for each item i this thread claims."""
    slot = claim_slot(claims)
    for item in claimed_items(claims, seen.shape[0], parts):
        seen[item] += 1
        slots[item] = slot


@pytest.fixture(params=THREADS, ids=lambda n: f"{n} threads")
def threads(request):
    before = numba.get_num_threads()
    numba.set_num_threads(request.param)
    yield request.param
    numba.set_num_threads(before)


@pytest.fixture(params=["numba's threads", "the helper team"])
def path(request, monkeypatch):
    """Each of run_parallel's two ways of running a loop on several threads."""
    if request.param == "the helper team":
        monkeypatch.setattr(cpu, "native_threads", lambda: False)
    elif not cpu.native_threads():
        pytest.skip("numba's threading layer here does not spin (workqueue): the team runs")
    return request.param


@pytest.mark.parametrize("count", [0, 1, 7, 1000, 100_003])
@pytest.mark.parametrize("parts", [None, 1, 3, 50])
def test_every_item_is_done_once_with_a_slot_of_its_threads_own(path, threads, count, parts):
    seen = np.zeros(count, dtype=np.int64)
    slots = np.full(count, -1, dtype=np.int64)
    run_parallel(_count_items, seen, slots, parts=parts)
    np.testing.assert_array_equal(seen, np.ones(count, dtype=np.int64))
    assert count == 0 or (slots.min() >= 0 and slots.max() < threads)


def test_claimed_parts_are_the_closed_form_in_order():
    # One thread claims every part: part p of P covers [count p // P, count (p + 1) // P).
    count, parts = 10, 4
    claims = np.zeros(3, dtype=np.int64)
    items = list(claimed_items(claims, count, parts))
    assert items == list(range(count))
    assert claims[NEXT_PART] == parts + 1 and claims[PARTS_DONE] == parts
    bounds = [count * p // parts for p in range(parts + 1)]
    assert bounds == [0, 2, 5, 7, 10]


@parallel_part()
def _fail_on_the_second_thread(claims, parts, done):
    """Each part done[part] = 1, but the second thread to join raises; the first waits (a
    bounded spin) until every part is claimed, so the second gets one."""
    slot = claim_slot(claims)
    for part in claimed_items(claims, parts, parts):
        if slot == 1:
            raise ValueError("raised on the second thread")
        done[part] = 1
        spin_below(claims, NEXT_PART, parts, 30_000_000)


@pytest.mark.skipif(numba.config.NUMBA_NUM_THREADS < 2, reason="needs a second thread")
def test_an_error_on_any_thread_is_raised_by_the_call(path, threads):
    if threads < 2:
        pytest.skip("needs a second thread")
    # numba's threads report that the loop failed; the helper team raises the loop's error
    with pytest.raises((RuntimeError, ValueError), match="failed on one of its threads|second"):
        run_parallel(_fail_on_the_second_thread, np.zeros(8, dtype=np.int64), parts=8)


def _items_done_in_a_child(count: int) -> list[int]:
    seen = np.zeros(count, dtype=np.int64)
    run_parallel(_count_items, seen, np.zeros(count, dtype=np.int64))
    return seen.tolist()


@pytest.mark.skipif(not hasattr(os, "fork"), reason="no fork on this platform")
def test_a_forked_child_runs_loops_with_threads_of_its_own():
    # on a helper team of its own where the parent's loops ran on GNU OpenMP's threads, which
    # a forked child cannot start again
    seen = np.zeros(5000, dtype=np.int64)
    run_parallel(_count_items, seen, np.zeros(5000, dtype=np.int64), parts=8)
    with multiprocessing.get_context("fork").Pool(1) as pool:  # forked after threads ran
        assert pool.apply(_items_done_in_a_child, (5000,)) == [1] * 5000


def _desk_run_on(threads: int):
    """The cpu pipeline over the warm-up's three 160x120 desk frames (icp+rgbd, 64^3) on
    `threads` threads: the poses, and the volume's TSDF and weights as the host sees them."""
    from kintinuous_fast import load_backend
    from kintinuous_ref.config import Config
    from kintinuous_ref.pipeline import run
    from kintinuous_ref.program.warmup import small_config, warmup_frames

    frames, camera, trajectory = warmup_frames()
    before = numba.get_num_threads()
    numba.set_num_threads(threads)
    try:
        result = run(
            frames, camera, small_config(Config()), "icp+rgbd", trajectory, load_backend("cpu")
        )
    finally:
        numba.set_num_threads(before)
    volume = result.host_volume(result.volume)
    return np.stack(result.poses), volume.tsdf, volume.weight


@pytest.mark.skipif(len(THREADS) < 2, reason="needs two threads")
def test_the_pipeline_gives_the_same_bits_on_one_and_two_threads():
    for one, two in zip(_desk_run_on(1), _desk_run_on(2), strict=True):
        np.testing.assert_array_equal(one, two)


@parallel_part()
def _write_after_the_signal(claims, parts, signalled, written):
    """Each part waits (a bounded spin) until signalled[0] is set, then sets written[part]; the
    thread that joins second writes tens of milliseconds later (a bounded spin), so that a
    call that returned before its other threads were done would miss those writes."""
    slot = claim_slot(claims)
    for part in claimed_items(claims, parts, parts):
        spin_below(signalled, 0, 1, 300_000_000)
        if slot > 0:
            spin_below(signalled, 0, 2, 2_000_000)  # signalled[0] never reaches 2
        written[part] = 1


def test_a_signal_during_a_loop_is_raised_once_every_part_is_done(path, threads):
    # a run that a signal ends keeps whole frames: no thread writes into a loop's outputs after
    # the call has raised
    signalled, written = np.ones(1, dtype=np.int64), np.zeros(2 * threads, dtype=np.int64)
    run_parallel(_write_after_the_signal, signalled, written, parts=written.size)  # compiled
    signalled[0], written[:] = 0, 0
    LOOP_COSTS.per_item.pop(_write_after_the_signal)  # unknown work again: every thread joins

    def interrupt() -> None:  # Ctrl-C while the loop runs
        _thread.interrupt_main()
        signalled[0] = 1

    # Python's own handler, which interrupt_main needs: a process started in the background
    # by a shell without job control inherits SIGINT ignored, and Python then installs none.
    handler = signal.signal(signal.SIGINT, signal.default_int_handler)
    timer = threading.Timer(0.05, interrupt)
    try:
        with pytest.raises(KeyboardInterrupt):
            timer.start()
            run_parallel(_write_after_the_signal, signalled, written, parts=written.size)
    finally:
        timer.join()
        signal.signal(signal.SIGINT, handler)
    np.testing.assert_array_equal(written, 1)


@pytest.mark.parametrize("count", [0, 5, 99, 100, 1000])
def test_loops_below_the_minimum_run_in_one_part_on_the_calling_thread(path, threads, count):
    seen = np.zeros(count, dtype=np.int64)
    slots = np.full(count, -1, dtype=np.int64)
    run_parallel_above(100, _count_items, count, seen, slots)
    np.testing.assert_array_equal(seen, np.ones(count, dtype=np.int64))
    if count < 100:  # one part: a single thread, slot 0, did every item
        np.testing.assert_array_equal(slots, np.zeros(count, dtype=np.int64))


# The child: numba's 7 threads, one call whose work is unknown (every thread may join), then
# calls that the work rule gives two threads; prints how many threads ran each call's parts.
JOIN_CHILD = """
import json
import numba, numpy as np
from kintinuous_fast.targets import cpu
from test_cpu_parts import _record_threads, _threads_of_parts

first = np.full(7 * cpu.PARTS_PER_THREAD, -1, dtype=np.int64)
cpu.run_parallel(_record_threads, first, True, items=100)
pairs = [len(set(_threads_of_parts(2.5, hold=True).tolist()) - {-1}) for _ in range(20)]
threads = numba.get_num_threads()
first = len(set(first.tolist()))
print(json.dumps({"first": first, "pairs": sorted(set(pairs)), "after": threads}))
"""


@pytest.mark.skipif(not cpu.native_threads(), reason="numba's threading layer does not spin")
def test_a_call_runs_on_as_many_threads_as_its_work_wants():
    result = run_with_threads(JOIN_CHILD, 7, timeout=300)
    assert 2 <= result["first"] <= 7  # unknown work: any of the 7 threads may join
    assert result["pairs"] == [2]  # two threads' work: two threads, never more
    assert result["after"] == 7  # and the calls leave the thread count as it was


# The child: a team of 6 helpers (NUMBA_NUM_THREADS=7), all asleep, then one call that wants
# exactly one helper (parts=2 on two threads); prints how many helpers looked at the job.
WAKE_CHILD = """
import json, time
import numba, numpy as np
from kintinuous_fast.targets import cpu
from test_cpu_threads import _count_items

cpu.native_threads = lambda: False  # the helper team's calls
looked = []
help_job = cpu._Job.help
cpu._Job.help = lambda job: (looked.append(1), help_job(job))[1]
seen, slots = np.zeros(10_000, dtype=np.int64), np.zeros(10_000, dtype=np.int64)
numba.set_num_threads(7)
cpu.run_parallel(_count_items, seen, slots, parts=7)  # starts the team, every helper joins
deadline = time.monotonic() + 30
while cpu._team().sleeping < 6 and time.monotonic() < deadline:  # each spins, then sleeps
    time.sleep(0.01)
asleep = cpu._team().sleeping
looked.clear()
numba.set_num_threads(2)
cpu.run_parallel(_count_items, seen, slots, parts=2)
time.sleep(0.2)  # a helper woken for nothing would have looked by now
print(json.dumps({"asleep": asleep, "looked": len(looked), "seen": sorted(set(seen.tolist()))}))
"""


def test_a_call_wakes_only_the_sleeping_helpers_it_wants():
    # each helper woken takes the GIL to look at the job, so waking a whole team for a loop
    # that wants one helper costs that loop the team's wake-ups (docs/benchmarks.md)
    result = run_with_threads(WAKE_CHILD, 7, timeout=300)
    assert result["asleep"] == 6
    assert result["looked"] <= 1  # the one helper wanted (or none: the caller took both parts)
    assert result["seen"] == [2]  # every item done once by each of the two calls


EDITED_LOOP = """
from kintinuous_fast.targets.cpu import claimed_items, parallel_part


@parallel_part()
def fill(claims, parts, out):
    for item in claimed_items(claims, out.shape[0], parts):
        out[item] = VALUE
"""
# The child: the edited loop's launcher on two threads; prints the values it wrote.
FILL_CHILD = """
import json, sys
import numpy as np
sys.path.insert(0, {folder!r})
import edited_loop
from kintinuous_fast.targets.cpu import launcher

out = np.zeros(100)
launcher(edited_loop.fill)(2, np.zeros(3, dtype=np.int64), 8, out)
print(json.dumps(sorted(set(out.tolist()))))
"""


def test_a_launcher_runs_its_loop_as_last_edited(tmp_path):
    # numba keeps each launcher, with its loop compiled in, in its on-disk cache: filed under
    # the loop's source file, it is dropped when that file changes, as the loop is
    module = tmp_path / "edited_loop.py"
    child = FILL_CHILD.format(folder=str(tmp_path))
    module.write_text(EDITED_LOOP.replace("VALUE", "1.0"))
    assert run_with_threads(child, 2, timeout=300) == [1.0]
    module.write_text(EDITED_LOOP.replace("VALUE", "2.0"))  # the same size: only its time differs
    later = module.stat().st_mtime_ns + 10**10
    os.utime(module, ns=(later, later))
    assert run_with_threads(child, 2, timeout=300) == [2.0]
