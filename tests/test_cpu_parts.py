"""How many threads a cpu loop runs on follows its work (kintinuous_fast.targets.cpu): the rule
in closed form, a loop below its work threshold seen to run on the calling thread alone (the
threads that ran its parts recorded), one above it shared, each loop's cost measured as it
runs; and the pipeline's poses and volume the same bits on 1, 2 and 7 threads, and with every
loop forced onto all 7."""

import json
import os
import subprocess
import sys
import textwrap
import threading
import time

import numba
import numpy as np
import pytest

from kintinuous_fast.targets import cpu
from kintinuous_fast.targets.cpu import (
    LOOP_COSTS,
    MIN_SECONDS_PER_THREAD,
    PARTS_PER_THREAD,
    LoopCosts,
    claimed_items,
    parallel_part,
    run_parallel,
    threads_for,
)


@pytest.fixture
def every_thread():
    """numba's thread count set to the most this process has, and put back."""
    before = numba.get_num_threads()
    numba.set_num_threads(numba.config.NUMBA_NUM_THREADS)
    yield numba.config.NUMBA_NUM_THREADS
    numba.set_num_threads(before)


def test_one_thread_per_minimum_of_work_and_all_while_the_work_is_unknown():
    unit = MIN_SECONDS_PER_THREAD
    assert threads_for(None, 7) == 7
    assert threads_for(0.0, 7) == 1
    assert threads_for(1.99 * unit, 7) == 1  # two threads only for two units of work
    assert threads_for(2.01 * unit, 7) == 2
    assert threads_for(5.5 * unit, 7) == 5
    assert threads_for(1000 * unit, 7) == 7
    assert threads_for(1000 * unit, 1) == 1


def test_a_loops_cost_is_its_seconds_per_item_times_the_items():
    costs = LoopCosts()
    assert costs.seconds("loop", 100) is None
    costs.record("loop", 1000, 2e-3)  # 2 microseconds an item
    assert costs.seconds("loop", 100) == pytest.approx(2e-4)
    assert costs.seconds("loop", 0) == pytest.approx(2e-6)  # never a zero cost for a call
    assert costs.seconds("other", 100) is None


def _recording_loop(idents):
    """A loop whose parts record the thread that ran them; the calling thread waits (up to
    10 s, however loaded the machine) for a helper to claim a part when there may be one."""

    def loop(claims, parts):
        for part in claimed_items(claims, parts, parts):
            idents[part] = threading.get_ident()
            if threading.current_thread() is threading.main_thread() and loop.shared:
                deadline = time.monotonic() + 10.0
                while claims[0] < parts and time.monotonic() < deadline:
                    time.sleep(0.001)

    return loop


def test_a_loop_below_its_work_threshold_runs_on_the_calling_thread_alone(every_thread):
    idents = {}
    loop = _recording_loop(idents)
    loop.shared = False
    LOOP_COSTS.record(loop, 100, 1.9 * MIN_SECONDS_PER_THREAD)  # less than two threads' work
    run_parallel(loop, items=100)
    assert len(idents) == PARTS_PER_THREAD  # the parts of one thread
    assert set(idents.values()) == {threading.get_ident()}


@pytest.mark.skipif(numba.config.NUMBA_NUM_THREADS < 2, reason="needs a helper thread")
def test_a_loop_above_its_work_threshold_is_shared(every_thread):
    idents = {}
    loop = _recording_loop(idents)
    loop.shared = True
    LOOP_COSTS.record(loop, 100, 2.5 * MIN_SECONDS_PER_THREAD)  # two threads' work
    run_parallel(loop, items=100)
    assert len(idents) == 2 * PARTS_PER_THREAD
    assert len(set(idents.values())) == 2  # the calling thread and one helper
    assert threading.get_ident() in idents.values()


@parallel_part()
def _squares(claims, parts, values, out):  # noqa: ANN001, ANN202
    for i in claimed_items(claims, values.shape[0], parts):
        out[i] = values[i] * values[i]


def test_each_call_measures_its_loops_cost(every_thread):
    values = np.arange(1000.0)
    out = np.zeros(1000)
    run_parallel(_squares, values, out)  # the first call: every thread, then measured
    run_parallel(_squares, values, out)
    np.testing.assert_array_equal(out, values * values)
    seconds = LOOP_COSTS.seconds(_squares, values.size)
    # a thousand multiplications: far below a thread's share of work on any machine that is
    # not stalled, and above nothing
    assert 0 < seconds < 0.5


# The child: the cpu pipeline over six 160x120 desk frames (icp+rgbd, 64^3) on each thread
# count, and once with every loop on all 7 threads (no work threshold); prints each run's
# poses and volume as SHA-256 digests of their bytes.
CHILD = textwrap.dedent(
    """
    import hashlib, json, numba
    import numpy as np
    from kintinuous_fast import load_backend
    from kintinuous_fast.targets import cpu
    from kintinuous_ref.config import Config
    from kintinuous_ref.datasets.synthetic import make_scenario
    from kintinuous_ref.pipeline import run
    from kintinuous_ref.program.warmup import small_config
    from kintinuous_ref.datasets.tum import Frame

    scenario = make_scenario("desk", frames=6, width=160, height=120)
    stamps = scenario.trajectory.timestamps
    frames = [Frame(i, float(stamps[i]), *scenario.render(i)) for i in range(6)]

    def digests(threads, minimum):
        numba.set_num_threads(threads)
        cpu.MIN_SECONDS_PER_THREAD = minimum
        result = run(frames, scenario.camera, small_config(Config()), "icp+rgbd",
                     scenario.trajectory, load_backend("cpu"))
        volume = result.host_volume(result.volume)
        arrays = (np.stack(result.poses), volume.tsdf, volume.weight)
        return [hashlib.sha256(np.ascontiguousarray(a).tobytes()).hexdigest() for a in arrays]

    minimum = cpu.MIN_SECONDS_PER_THREAD
    runs = {f"{n} threads": digests(n, minimum) for n in (1, 2, 7)}
    runs["7 threads, every loop shared"] = digests(7, 1e-12)
    print(json.dumps(runs))
    """
)


def test_the_pipeline_gives_the_same_bits_on_1_2_and_7_threads():
    environment = {**os.environ, "NUMBA_NUM_THREADS": "7"}
    child = subprocess.run(
        [sys.executable, "-c", CHILD],
        env=environment,
        capture_output=True,
        text=True,
        timeout=1200,
        check=False,
    )
    assert child.returncode == 0, child.stderr[-3000:]
    runs = json.loads(child.stdout.strip().splitlines()[-1])
    first = runs["1 threads"]
    for name, digests in runs.items():
        assert digests == first, name
    assert cpu.MIN_SECONDS_PER_THREAD == MIN_SECONDS_PER_THREAD  # the child's change stays there
