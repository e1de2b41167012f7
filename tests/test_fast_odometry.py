"""Equivalence of kintinuous_fast's CPU odometry (kintinuous_fast.odometry.cpu) with
kintinuous_ref.odometry on small frames (80x60 and 160x120 of the analytic room), degenerate
inputs (no depth, an empty frustum, points on the image borders) and whole trackers after 1 and 3
iterations and at convergence. Cases and tolerances: tests/test_fast_odometry_cases.py.

The CUDA twin is tests/test_fast_odometry_cuda.py: on a GPU it runs directly; without one, the
last test here runs it in a child process on numba's CUDA simulator."""

from pathlib import Path

import numpy as np
import pytest
import test_fast_odometry_cases as cases

import kintinuous_fast
from kintinuous_fast import load_backend
from kintinuous_fast.odometry import cpu
from kintinuous_fast.odometry.icp import cpu as icp_cpu
from kintinuous_fast.odometry.rgbd import cpu as rgbd_cpu
from kintinuous_ref.config import Config, fast_odometry
from kintinuous_ref.errors import ConfigError, DatasetError
from kintinuous_ref.odometry import DenseTracker

SIZES = [(80, 60), (160, 120)]
IDS = ["80x60", "160x120"]
CPU = cases.functions("cpu")  # the cpu modules' public functions, for the shared checks


@pytest.mark.parametrize("size", SIZES, ids=IDS)
@pytest.mark.parametrize("check", cases.LEVEL_CHECKS, ids=cases.check_id)
def test_equivalence_cpu_odometry(check, size):
    check(CPU, *size)


@pytest.mark.parametrize("count", [1, 63, 5000])
def test_equivalence_cpu_accumulate(count):
    cases.check_accumulate(CPU, count)


def test_cpu_lists_keep_the_reference_order():
    # Chunked loops + host compaction: no sorting needed on the CPU (unlike CUDA's atomics).
    data, camera = cases.level_inputs(160, 120)
    args = (data.depth, data.intensity, data.intensity_dx, data.intensity_dy, camera, 5.0, 6.0)
    from kintinuous_ref.odometry import rgbd

    np.testing.assert_array_equal(
        rgbd_cpu.prepare_level(*args).indices, rgbd.prepare_level(*args).indices
    )


def test_equivalence_cpu_repeated_streams():
    # The compiled comparisons stop early; their answers are np.array_equal's and np.any's.
    from types import SimpleNamespace

    from kintinuous_ref.odometry import repeated_streams

    rng = np.random.default_rng(3)
    depth = rng.uniform(0.5, 4.0, (60, 80)).astype(np.float32)
    intensity = rng.uniform(0, 255, (60, 80)).astype(np.float32)

    def frame(depth, intensity):  # noqa: ANN001, ANN202 (what repeated_streams reads)
        return SimpleNamespace(levels=[SimpleNamespace(depth=depth, intensity=intensity)])

    last_pixel = depth.copy()
    last_pixel[-1, -1] += 1e-3
    with_nan = depth.copy()
    with_nan[30, 40] = np.nan
    blind = np.zeros_like(depth)
    first = frame(depth, intensity)
    cases = [
        (first, frame(depth.copy(), intensity.copy()), (True, True)),
        (first, frame(last_pixel, intensity), (False, True)),
        (first, frame(depth, intensity[::-1].copy()), (True, False)),
        (frame(with_nan, intensity), frame(with_nan.copy(), intensity), (False, True)),
        (frame(blind, intensity), frame(blind.copy(), intensity), (False, False)),
        (first, frame(depth[:, :40], intensity[:, :40]), (False, False)),
        (None, first, (False, False)),
    ]
    for previous, current, expected in cases:
        assert repeated_streams(previous, current) == expected
        assert cpu.repeated_streams(previous, current) == expected


# Poses after a fixed number of iterations: every row agrees to ~1 ulp and every sum to ~1e-12
# relative, so one Gauss-Newton step agrees to ~1e-12 m; the brief's bound 1e-6 m / 1e-5 rad
# leaves room for the CUDA sums' atomic order. At convergence both stop at the same step (their
# steps agree to ~1e-12, so neither lands on the other side of the 1e-5 threshold by chance):
# 1e-6 m / 1e-5 rad as well.
FIXED = (1e-6, 1e-5)


@pytest.mark.parametrize("method", ["icp", "rgbd", "icp+rgbd"])
@pytest.mark.parametrize("iterations", [(1, 1, 1), (3, 3, 3), None], ids=["1", "3", "converged"])
def test_equivalence_cpu_tracker(method, iterations):
    reference, truth = cases.check_tracker(cpu.make_tracker, method, 160, 120, iterations, FIXED)
    if iterations is None:  # and the reference itself recovers the known motion
        metres, radians = cases.pose_difference(reference, truth)
        assert metres < 2e-3 and radians < np.radians(0.2), (metres, radians)


@pytest.mark.parametrize(
    ("method", "overrides"),
    [
        ("icp", {"icp.robust_kernel": "huber"}),
        ("icp", {"icp.robust_kernel": "tukey", "icp.robust_noise": 0.003}),
        ("icp+rgbd", {"combined.weighting": "huber"}),
        ("icp+rgbd", {"combined.weighting": "tukey"}),
        ("icp", {"icp.robust_kernel": "none"}),
        ("icp+rgbd", {"combined.weighting": "degeneracy-aware"}),
        ("icp", {"icp.depth_noise": False}),
    ],
    ids=[
        "icp-huber",
        "icp-tukey",
        "combined-huber",
        "combined-tukey",
        "icp-least-squares",
        "combined-least-squares",
        "icp-huber-no-depth-noise",
    ],
)
def test_equivalence_cpu_tracker_robust(method, overrides):
    cases.check_tracker(cpu.make_tracker, method, 160, 120, (3, 3, 3), FIXED, overrides)


def test_cpu_inlier_fraction_counts_the_reference_pairs():
    # The CPU counts the pairs without the sums (icp/cpu.py's _points_pairs): the same
    # integers.
    from kintinuous_ref.odometry.icp import IcpProblem
    from kintinuous_ref.preprocess import model_pyramid

    camera, previous, current, _, frame, rendered = cases.room(160, 120)
    model = model_pyramid(*rendered[0], 3)  # as the trackers build it: strided coarse levels
    assert not model[1][0].flags.c_contiguous
    for thresholds in ((0.10, 20.0), (0.01, 5.0)):
        fast = cpu.IcpProblem(frame.levels, model, previous, *thresholds)
        reference = IcpProblem(frame.levels, model, previous, *thresholds)
        for pose in cases.poses_to_try(previous, current):
            assert fast.inlier_fraction(pose) == reference.inlier_fraction(pose)
    for level in range(1, 3):  # staged strided maps equal NumPy's copies
        for fast_map, reference_map in zip(fast.model(level), model[level], strict=True):
            assert fast_map.flags.c_contiguous
            np.testing.assert_array_equal(fast_map, reference_map)


def test_equivalence_cpu_tracker_fovis_switching():
    # FOVIS itself is the reference's (CPU, as in the paper); the dense half is the fast one, so
    # the switched result equals the reference tracker's.
    cases.check_tracker(cpu.make_tracker, "fovis/icp+rgbd", 160, 120, None, FIXED)


def test_equivalence_cpu_tracker_failure():
    # A current frame without depth: both trackers fail with the same reason and fallback pose.
    camera, previous, _, previous_frame, frame, _ = cases.room(160, 120, 4)
    import odometry_scene as scene

    empty = scene.Frame(
        [
            scene.Level(level.camera, np.zeros_like(level.depth),
                        np.full_like(level.vertices, np.nan), np.full_like(level.normals, np.nan),
                        level.intensity, level.intensity_dx, level.intensity_dy)
            for level in frame.levels
        ]
    )  # fmt: skip
    vertices, normals = scene.model(previous, camera, 1)[0]
    model = cases.Model(previous, vertices, normals)
    for method in ("icp", "rgbd", "icp+rgbd"):
        fast = cpu.make_tracker(method, Config(), camera)
        result = fast.track(previous_frame, empty, model, previous)
        assert not result.ok and "too few correspondences" in result.reason
        np.testing.assert_array_equal(result.pose, previous)


def test_make_tracker_backends_and_errors():
    camera = cases.room(80, 60)[0]
    assert load_backend("cpu").odometry is cpu
    assert load_backend("ref").odometry.__name__ == "kintinuous_ref.odometry"
    with pytest.raises(ConfigError, match="unknown odometry method 'kinfu'"):
        cpu.make_tracker("kinfu", Config(), camera)
    with pytest.raises(ConfigError, match="unknown backend 'gpu'"):
        load_backend("gpu")
    # The backend module has the reference's make_tracker (its systems by default) and the
    # reference's own DenseTracker.
    assert cpu.make_tracker("icp+rgbd", Config(), camera).systems is cpu
    assert cpu.make_tracker("rgbd", Config(), camera).systems is cpu
    assert cpu.DenseTracker is DenseTracker
    with pytest.raises(ConfigError, match="unknown odometry method 'kinfu'"):
        cpu.make_tracker("kinfu", Config(), camera)
    fovis = cpu.make_tracker("fovis/icp+rgbd", Config(), camera)
    assert fovis.dense.systems is cpu  # the dense half is the fast one, FOVIS the reference's
    level = cases.room(80, 60)[4].levels[0]
    with pytest.raises(
        DatasetError, match=r"model vertex map is \(30, 40, 3\), expected \(60, 80, 3\)"
    ):
        icp_cpu.icp_system(level.vertices, level.normals, np.eye(4), level.vertices[::2, ::2],
                       level.normals, np.eye(4), camera)  # fmt: skip


def test_cpu_icp_helpers_are_the_reference_system_and_valid_count():
    # _current_points (the valid current points, compacted once per level) and _points_system
    # (their sums) are the halves of the CPU's icp_system that the per-frame problem calls: the
    # reference's system with Huber and depth noise weights, and the number of valid current
    # vertices the inlier fraction divides by; the per-frame problem passes the inverse model
    # pose it computes once.
    from kintinuous_fast.odometry.icp import icp_constants, robust_terms
    from kintinuous_ref import se3
    from kintinuous_ref.odometry import icp as ref_icp

    camera, previous, current, _, frame, model = cases.room(160, 120)
    level, pose = frame.levels[0], cases.poses_to_try(previous, current)[-1]
    noise, threshold = ref_icp.voxel_noise(3.0 / 256), ref_icp.robust_threshold("huber", 0.005)
    reference = ref_icp.icp_system(level.vertices, level.normals, pose, *model[0], previous,
                                   camera, 0.10, 20.0, "huber", 0.005, noise)  # fmt: skip
    valid = ref_icp.valid_points(level.vertices, level.normals)[0].shape[1]
    weights = robust_terms("huber", threshold, noise)
    points = icp_cpu._current_points(level.vertices, level.normals, camera)
    for name, inverse in (
        ("icp_system_and_valid", None),
        ("icp_points_system", se3.inverse(previous)),
    ):
        constants = icp_constants(pose, previous, 0.10, 20.0, inverse)
        system, count = icp_cpu._points_system(points, model[0], camera, constants, weights)
        cases.assert_systems_close(name, system, reference)
        assert count == valid
    # Images of different sizes: a one-line DatasetError naming the one that does not fit.
    with pytest.raises(DatasetError, match=r"intensity_dy is \(120, 159\), expected \(120, 160\)"):
        rgbd_cpu.interest_points(level.intensity_dx, level.intensity_dy[:, 1:], 5.0)


def test_fast_odometry_skips_the_finest_level():
    config = fast_odometry(Config())
    assert config.icp.iterations == (0, 5, 4)
    assert config.rgbd.combined_iterations == (0, 5, 4)
    assert config.rgbd.iterations == (0, 7, 7, 7)
    # ... and still tracks the room's known motion to a few millimetres from level 1 alone.
    camera, previous, current, previous_frame, frame, _ = cases.room(160, 120, 4)
    import odometry_scene as scene

    vertices, normals = scene.model(previous, camera, 1)[0]
    result = cpu.make_tracker("icp+rgbd", config, camera).track(
        previous_frame, frame, cases.Model(previous, vertices, normals), previous
    )
    metres, radians = cases.pose_difference(result.pose, current)
    assert result.ok and metres < 5e-3 and radians < np.radians(0.3), (metres, radians)


@pytest.mark.skipif(
    kintinuous_fast.cuda_status() == "",
    reason="CUDA works in this process: tests/test_fast_odometry_cuda.py runs directly",
)
@pytest.mark.cuda_simulator(Path(__file__).parent / "test_fast_odometry_cuda.py")
def test_equivalence_cuda_odometry_in_simulator(cuda_simulator):
    cuda_simulator()
