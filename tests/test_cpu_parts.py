"""How many threads a cpu loop runs on follows its work (kintinuous_fast.targets.cpu): the rule
in closed form, a loop below its work threshold seen to run on the calling thread alone (the
threads that ran its parts recorded), one above it shared, each loop's cost measured as it
runs; the pipeline's poses and volume the same bits on 1, 2 and 7 threads, and with every
loop forced onto all 7, on numba's threads and on the helper team; and the joint ICP + RGB-D
loop (one parallel call per iteration) the same bits as the two problems' separate systems
summed, on each of those, and close to the reference's joint system; and solve.refine, which runs
a level's steps in one compiled call, the poses and failures of the reference's loop."""

import textwrap

import numba
import numpy as np
import pytest
from threads_child import run_with_threads

from kintinuous_fast.targets import cpu
from kintinuous_fast.targets.cpu import (
    LOOP_COSTS,
    MIN_SECONDS_PER_HELPER,
    MIN_SECONDS_PER_THREAD,
    NEXT_PART,
    PARTS_PER_THREAD,
    LoopCosts,
    claim_slot,
    claimed_items,
    parallel_part,
    planned_team,
    run_parallel,
    spin_below,
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


def test_a_loops_team_follows_its_measured_work(every_thread):
    """planned_team, which run_parallel and a level's compiled loop both ask: threads_for of the
    work last measured, on numba's threads where they spin (else the helper team's minimum)."""
    native = every_thread > 1 and cpu.native_threads()
    minimum = MIN_SECONDS_PER_THREAD if native else MIN_SECONDS_PER_HELPER

    def loop():  # a key of its own in LOOP_COSTS
        pass

    assert planned_team(loop, 100) == (every_thread, native)  # not yet measured: every thread
    LOOP_COSTS.record(loop, 100, 2.5 * minimum)
    assert planned_team(loop, 100) == (min(2, every_thread), native)
    assert planned_team(loop, 1000) == (min(25, every_thread), native)


@parallel_part()
def _record_threads(claims, parts, thread_of_part, hold):  # noqa: ANN001, ANN202
    """thread_of_part[p] = the slot (claim_slot: one per thread that joins) of the thread that
    ran part p. With `hold`, the first thread to join waits (up to some seconds, however loaded
    the machine) until every part is claimed, so that another thread that joins gets a part."""
    slot = claim_slot(claims)
    for part in claimed_items(claims, parts, parts):
        thread_of_part[part] = slot
        if hold and slot == 0:
            spin_below(claims, NEXT_PART, parts, 300_000_000)


def _threads_of_parts(work_units: float, hold: bool) -> np.ndarray:
    """The slot of the thread that ran each part of a call of _record_threads whose measured
    work is `work_units` times the least work a thread joins for (-1: no such part)."""
    thread_of_part = np.full(PARTS_PER_THREAD * numba.get_num_threads(), -1, dtype=np.int64)
    minimum = MIN_SECONDS_PER_THREAD if cpu.native_threads() else MIN_SECONDS_PER_HELPER
    LOOP_COSTS.record(_record_threads, 100, work_units * minimum)
    run_parallel(_record_threads, thread_of_part, hold, items=100)
    return thread_of_part


def test_a_loop_below_its_work_threshold_runs_on_the_calling_thread_alone(every_thread):
    thread_of_part = _threads_of_parts(1.9, hold=False)  # less than two threads' work
    np.testing.assert_array_equal(thread_of_part[:PARTS_PER_THREAD], 0)  # one thread's parts
    assert (thread_of_part[PARTS_PER_THREAD:] == -1).all()


@pytest.mark.skipif(numba.config.NUMBA_NUM_THREADS < 2, reason="needs a second thread")
def test_a_loop_above_its_work_threshold_is_shared(every_thread):
    thread_of_part = _threads_of_parts(2.5, hold=True)  # two threads' work
    assert (thread_of_part[: 2 * PARTS_PER_THREAD] >= 0).all()
    assert (thread_of_part[2 * PARTS_PER_THREAD :] == -1).all()
    assert set(thread_of_part[thread_of_part >= 0]) == {0, 1}  # two threads, each with parts


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
# count and path, and with every loop on all 7 threads (no work threshold); prints each run's
# poses and volume as SHA-256 digests of their bytes.
CHILD = textwrap.dedent(
    """
    import hashlib, json, numba
    import numpy as np
    from threads_child import on_both_paths
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

    def digests(threads):
        numba.set_num_threads(threads)
        result = run(frames, scenario.camera, small_config(Config()), "icp+rgbd",
                     scenario.trajectory, load_backend("cpu"))
        volume = result.host_volume(result.volume)
        arrays = (np.stack(result.poses), volume.tsdf, volume.weight)
        return [hashlib.sha256(np.ascontiguousarray(a).tobytes()).hexdigest() for a in arrays]

    print(json.dumps(on_both_paths(digests)))
    """
)


def test_the_pipeline_gives_the_same_bits_on_1_2_and_7_threads():
    runs = run_with_threads(CHILD, 7)
    assert len(runs) == 8
    first = runs["the helper team, 1 threads"]
    for name, digests in runs.items():
        assert digests == first, name
    assert cpu.MIN_SECONDS_PER_THREAD == MIN_SECONDS_PER_THREAD  # the child's change stays there


# The child: the joint ICP + RGB-D system of the analytic room (160x120, three levels, three
# poses) from the fused loop (icp/cpu_joint.py, what CombinedProblem.system runs on the CPU) and
# from the two problems' separate systems summed by combined.joint_system, on each thread count
# and path, and with every loop forced onto all 7; prints each run's systems as SHA-256 digests of
# their bytes, and each problem's RGB-D inlier fraction beside the base class's.
JOINT_CHILD = textwrap.dedent(
    """
    import hashlib, json, numba
    import numpy as np
    import test_fast_odometry_cases as cases
    from threads_child import on_both_paths  # the tests folder is on the child's path
    from kintinuous_fast.odometry import combined, cpu as odometry
    from kintinuous_fast.odometry.solve import apply_increment, refine, solve
    from kintinuous_fast.targets import cpu
    from kintinuous_ref.odometry import solve as reference_solve
    from kintinuous_ref.odometry.rgbd import RgbdProblem
    from kintinuous_ref.preprocess import model_pyramid

    camera, previous, current, previous_frame, frame, rendered = cases.room(160, 120)
    model = model_pyramid(*rendered[0], 3)

    def problems():
        icp = odometry.IcpProblem(frame.levels, model, previous, 0.1, 20.0, "huber", 0.01)
        return icp, odometry.RgbdProblem(previous_frame.levels, frame.levels, previous)

    def digest(system):
        parts = (system.A, system.b, np.array([system.count, system.cost]))
        return hashlib.sha256(b"".join(p.tobytes() for p in parts)).hexdigest()

    def systems(threads):
        numba.set_num_threads(threads)
        fused, separate, fractions = [], [], []
        joint = combined.CombinedProblem(*problems(), 0.3, "huber")
        for pose in cases.poses_to_try(previous, current):
            for level in range(3):
                for _ in range(2):  # the level's work arrays serve every iteration
                    fused.append(digest(joint.system(level, pose)))
                icp, rgbd = problems()
                summed = combined.joint_system(
                    icp.system(level, pose), rgbd.system(level, pose), 0.3, "huber", 10.0,
                    pose[:3, 3], joint.degeneracy_threshold,
                )
                separate.append(digest(summed))
                base = RgbdProblem.inlier_fraction(rgbd, pose, level)
                fractions.append((rgbd.inlier_fraction(pose, level), base))
        return {"fused": fused, "separate": separate, "fractions": fractions}

    def problem(kind):
        # (the problem, the one its levels are kept on)
        if kind == "icp+rgbd":
            joint = combined.CombinedProblem(*problems(), 0.3, "huber")
            return joint, joint.icp
        alone = problems()[0 if kind == "icp" else 1]
        return alone, alone

    def refined(threads):
        # each level's steps in compiled code (solve.refine, JointLevel.refine) and stepped by
        # the reference's loop with the compiled step, over the joint problem and each term's
        # alone; the second least count fails a step
        numba.set_num_threads(threads)
        runs = {"compiled": [], "stepped": [], "levels in compiled code": []}
        step, steps = (solve, apply_increment), (4, 3, 3)
        for pose in cases.poses_to_try(previous, current):
            for least in (6, 10**9):
                for kind in ("icp+rgbd", "icp", "rgbd"):
                    fresh, owner = problem(kind)
                    runs["compiled"].append(refine(pose, fresh.system, steps, least, 1e-6))
                    again, _ = problem(kind)
                    stepped = reference_solve.refine(pose, again.system, steps, least, 1e-6, step)
                    runs["stepped"].append(stepped)
                    levels = owner.__dict__.get("_joint_levels", {}).values()
                    runs["levels in compiled code"].append(sum(lv.steps > 0 for lv in levels))
        for name in ("compiled", "stepped"):
            runs[name] = [(digest_pose(pose), reason) for pose, reason in runs[name]]
        return {**runs, "native": cpu.native_threads()}

    def digest_pose(pose):
        return hashlib.sha256(np.ascontiguousarray(pose).tobytes()).hexdigest()

    print(json.dumps({**on_both_paths(systems), "refine": on_both_paths(refined)}))
    """
)


@pytest.fixture(scope="module")
def joint_child_runs():
    """JOINT_CHILD's output, run once for the tests that read it."""
    return run_with_threads(JOINT_CHILD, 7)


def test_a_level_in_compiled_code_takes_the_reference_loops_steps(joint_child_runs):
    """solve.refine over the CPU's joint problem, and over its ICP and RGB-D problems alone,
    runs each level's steps in one compiled call wherever the loop runs on numba's threads or on
    the calling thread alone, and ends with the pose and the failure (a least count no level
    reaches) of the reference's loop stepping through the same problem, bit for bit, on every
    thread count and path."""
    runs = joint_child_runs["refine"]
    assert len(runs) == 8
    first = runs["the helper team, 1 threads"]
    for name, run in runs.items():
        assert run["compiled"] == run["stepped"] == first["compiled"], name
        in_compiled_code = run["native"] or name.endswith(" 1 threads")
        # every level where each level is reached, the coarsest where its first step fails;
        # the joint, ICP and RGB-D problems for each least count
        expected = [3, 3, 3, 1, 1, 1] if in_compiled_code else [0] * 6
        expected *= len(run["compiled"]) // 6
        assert run["levels in compiled code"] == expected, name
    reasons = [reason for _, reason in first["compiled"]]
    for at in range(0, len(reasons), 6):
        assert reasons[at : at + 3] == ["", "", ""]
        failed = reasons[at + 3 : at + 6]
        assert all(r.startswith("level 2: too few correspondences (") for r in failed)


def test_the_joint_loop_gives_the_separate_systems_bits_on_1_2_and_7_threads(joint_child_runs):
    runs = {name: run for name, run in joint_child_runs.items() if name != "refine"}
    assert len(runs) == 8
    first = runs["the helper team, 1 threads"]
    for name, run in runs.items():
        # two calls at each pose and level, and the separate systems' sum once
        assert run["fused"][::2] == run["fused"][1::2] == run["separate"], name
        assert run == first, name
        for fast, base in run["fractions"]:
            assert fast == base and 0.5 < fast <= 1.0, name


def test_the_joint_system_is_the_references():
    """The fused loop's joint system against kintinuous_ref's CombinedProblem, an independent
    implementation (NumPy products and sums), at every level and pose, to the summation
    tolerances of tests/test_fast_odometry_cases.py."""
    import test_fast_odometry_cases as cases

    from kintinuous_fast.odometry import cpu as odometry
    from kintinuous_ref.odometry import combined, icp, rgbd
    from kintinuous_ref.preprocess import model_pyramid

    camera, previous, current, previous_frame, frame, rendered = cases.room(160, 120)
    model = model_pyramid(*rendered[0], 3)
    icp_arguments = (frame.levels, model, previous, 0.1, 20.0, "huber", 0.01)
    rgbd_arguments = (previous_frame.levels, frame.levels, previous)
    fast = odometry.CombinedProblem(
        odometry.IcpProblem(*icp_arguments), odometry.RgbdProblem(*rgbd_arguments), 0.3, "huber"
    )
    reference = combined.CombinedProblem(
        icp.IcpProblem(*icp_arguments), rgbd.RgbdProblem(*rgbd_arguments), 0.3, "huber"
    )
    for pose in cases.poses_to_try(previous, current):
        for level in range(3):
            expected = reference.system(level, pose)
            assert expected.count > 100
            cases.assert_systems_close(
                f"level {level}",
                fast.system(level, pose),
                expected,
                residual_atol=cases.INTENSITY_ATOL,
            )
