"""Equivalence of kintinuous_fast's CUDA odometry (kintinuous_fast.odometry.cuda) with
kintinuous_ref.odometry, on a GPU or on numba's CUDA simulator.

Without a GPU these tests are skipped in the main pytest process and run in a child process with
NUMBA_ENABLE_CUDASIM=1 (the last test of tests/test_fast_odometry.py starts it). The simulator runs
every CUDA thread as a Python thread (~2 ms per pixel per kernel on the shared 2-core machine), so
there the frames are 40x30 (the reduction kernels' shared-memory trees and both list-building
algorithms still span ten blocks of 128 threads), each check tries one pose estimate instead of
three (cases.QUICK) and ICP+RGB-D (which runs both estimators' kernels) is tracked with one
iteration on each of two levels; on a GPU the sizes and cases of the CPU tests are used. Lists
come out in atomic order: the cases sort them. Cases and tolerances:
tests/test_fast_odometry_cases.py.
"""

import numpy as np
import pytest
import test_fast_odometry_cases as cases

from kintinuous_fast import cuda_is_simulated, cuda_status

pytestmark = pytest.mark.skipif(
    bool(cuda_status()),
    reason="no CUDA GPU: runs in the simulator subprocess of test_fast_odometry.py",
)

SIMULATED = cuda_is_simulated()
cases.QUICK = SIMULATED
SIZES = [(40, 30)] if SIMULATED else [(80, 60), (160, 120)]
FIXED = (1e-6, 1e-5)  # metres, radians: see test_fast_odometry.py


@pytest.fixture(scope="module")
def gpu():
    return cases.functions("cuda")


# joint_system is host code, the same as the cpu's: the simulator leaves it out.
CHECKS = [c for c in cases.LEVEL_CHECKS if not (SIMULATED and c is cases.check_joint_system)]


@pytest.mark.parametrize("size", SIZES, ids=lambda s: f"{s[0]}x{s[1]}")
@pytest.mark.parametrize("check", CHECKS, ids=cases.check_id)
def test_equivalence_cuda_odometry(gpu, check, size):
    check(gpu, *size)


@pytest.mark.parametrize("count", [1, 300] if SIMULATED else [1, 63, 5000])
def test_equivalence_cuda_accumulate(gpu, count):
    cases.check_accumulate(gpu, count)


@pytest.mark.parametrize("method", ["icp+rgbd"] if SIMULATED else ["icp", "rgbd", "icp+rgbd"])
def test_equivalence_cuda_tracker(method):
    from kintinuous_fast.odometry.cuda import make_tracker as tracker

    if SIMULATED:
        cases.check_tracker(tracker, method, *SIZES[0], (1, 1), FIXED)
    else:
        for iterations in ((1, 1, 1), (3, 3, 3), None):
            cases.check_tracker(tracker, method, 160, 120, iterations, FIXED)


@pytest.mark.parametrize("weighting", ["tukey"] if SIMULATED else ["huber", "tukey"])
def test_equivalence_cuda_tracker_robust(weighting):
    from kintinuous_fast.odometry.cuda import make_tracker as tracker

    size, iterations = (SIZES[0], (1, 1)) if SIMULATED else ((160, 120), (3, 3, 3))
    overrides = {"combined.weighting": weighting}
    cases.check_tracker(tracker, "icp+rgbd", *size, iterations, FIXED, overrides)


def test_equivalence_cuda_device_arrays_stay_on_device(gpu):
    # Device inputs: the interest points and the correspondences stay device arrays.
    from numba import cuda

    from kintinuous_fast.targets.cuda import is_device
    from kintinuous_ref.odometry import rgbd

    width, height = SIZES[0]
    data, camera = cases.level_inputs(width, height)
    on_device = [cuda.to_device(a) for a in (data.depth, data.intensity, data.intensity_dx,
                                              data.intensity_dy)]  # fmt: skip
    points = gpu.prepare_level(*on_device, camera, 5.0, 6.0)
    assert is_device(points.indices) and is_device(points.points)
    _, previous, current, previous_frame, _, _ = cases.room(width, height)
    prev = previous_frame.levels[0]
    pairs = gpu.correspond(points, current, previous, cuda.to_device(prev.depth),
                           cuda.to_device(prev.intensity), camera, 0.07)  # fmt: skip
    assert is_device(pairs.world) and is_device(pairs.kept)
    reference = rgbd.prepare_level(data.depth, data.intensity, data.intensity_dx,
                                   data.intensity_dy, camera, 5.0, 6.0)  # fmt: skip
    np.testing.assert_array_equal(np.sort(points.indices.copy_to_host()), reference.indices)
