"""Shared checks for the fast-odometry equivalence tests (no tests of its own: the CPU backend's
run in tests/test_fast_odometry.py, the CUDA backend's in tests/test_fast_odometry_cuda.py).

Each check calls a backend's function and its kintinuous_ref.odometry namesake on the same input
and compares. Inputs: the analytic textured room of tests/odometry_scene.py (exact geometry and
intensities, nothing from the code under test) at a given size, with a known camera motion.

Tolerances (justified once here, used below):
- Per-correspondence values (rows, residuals, points, warps) are computed by the kernels in
  float64 with the reference's formulas and order of operations; they may differ only by FMA
  contraction and the order of the 3-term dot products inside NumPy's matrix products, ~1 ulp
  (2.2e-16 relative). Compared with atol ROW_ATOL = 1e-12 (values are O(1..100): metres, pixels,
  intensity levels) and rtol ROW_RTOL = 1e-12 for Jacobian entries (up to ~1e4 for the
  photometric rows), a thousand times looser than seen, far below any quantity that matters.
  Intensity residuals I_n(p') - I_{n+1}(p) inherit the warp's rounding: delta u <= a few ulps of
  a pixel coordinate (<= 1e-13 px) times the steepest intensity change (<= 255 per pixel), so
  INTENSITY_ATOL = 1e-10 levels.
- Sums over N rows (the normal equations) are added in another order (chunks / tree vs BLAS):
  the error is at most N eps sum|terms| ~ 2e4 * 1.1e-16 = 2.2e-12 of sum|terms|. By
  Cauchy-Schwarz sum|J_i r| <= sqrt(A_ii cost), so A is compared to SUM_RTOL = 1e-10 of max|A|
  and b_i to 1e-10 sqrt(A_ii cost); counts must be equal.
- Lists (interest points, pairs) must be the same SETS; the CPU keeps the reference's order,
  CUDA lists come in atomic order and are sorted before comparing.
"""

from __future__ import annotations

import functools
import importlib
from collections.abc import Callable
from types import SimpleNamespace

import numpy as np
import odometry_scene as scene

from kintinuous_ref import se3
from kintinuous_ref.camera import Intrinsics
from kintinuous_ref.config import Config, with_overrides
from kintinuous_ref.odometry import combined as ref_combined
from kintinuous_ref.odometry import icp as ref_icp
from kintinuous_ref.odometry import make_tracker as ref_make_tracker
from kintinuous_ref.odometry import rgbd as ref_rgbd
from kintinuous_ref.odometry import solve as ref_solve

# Fewer cases per check (set by the CUDA tests on the simulator, where a kernel launch over a
# 40x30 frame costs seconds); the degenerate inputs are kept.
QUICK = False
ROW_ATOL = 1e-12
ROW_RTOL = 1e-12
INTENSITY_ATOL = 1e-10
SUM_RTOL = 1e-10
MOTION = se3.exp(np.array([0.01, -0.02, 0.015, 0.02, -0.01, 0.03]))


@functools.lru_cache(maxsize=8)
def room(width: int, height: int, levels: int = 3):
    """(camera, previous pose, current pose, previous frame, current frame, model pyramid)."""
    camera = scene.CAMERA.resized(width, height)
    previous = scene.look_pose([0.1, -0.1, 0.2], 5, -10)
    current = previous @ MOTION
    return (
        camera,
        previous,
        current,
        scene.frame(previous, camera, levels),
        scene.frame(current, camera, levels),
        scene.model(previous, camera, levels),
    )


def poses_to_try(previous: np.ndarray, current: np.ndarray) -> list[np.ndarray]:
    """The start of tracking (previous pose), the truth, and an estimate off by ~1 cm / 1 deg."""
    off = current @ se3.exp(np.array([0.01, 0.012, -0.008, 0.008, -0.011, 0.006]))
    return [off] if QUICK else [previous, current, off]


def functions(target: str) -> SimpleNamespace:
    """The public functions of a target's odometry (kintinuous_fast.odometry's icp, rgbd and
    solve modules of `target`, and combined), as one namespace the checks call."""
    names = (f"icp.{target}", f"rgbd.{target}", f"solve.{target}", "combined")
    namespace = SimpleNamespace()
    for name in names:
        module = importlib.import_module(f"kintinuous_fast.odometry.{name}")
        for public in module.__all__:
            setattr(namespace, public, getattr(module, public))
    return namespace


def host(array):
    return array.copy_to_host() if hasattr(array, "copy_to_host") else np.asarray(array)


# ----------------------------------------------------------------------------------------------
# Comparisons


def assert_systems_close(
    name: str, fast, reference, rtol: float = SUM_RTOL, residual_atol: float = ROW_ATOL
) -> None:
    """Counts equal; A to rtol max|A|; b_i and the cost to their summation bound (rtol times
    sum|terms|, by Cauchy-Schwarz <= sqrt(A_ii cost)) plus the propagated residual rounding:
    a residual that cancels (r = (p - q).n ~ 1e-7 m from p, q ~ 2 m) carries an absolute error
    of a few ulps of its operands, <= residual_atol, hence + residual_atol sum|J_i| <=
    residual_atol sqrt(count A_ii) on b_i and 2 residual_atol sqrt(count cost) on the cost."""
    assert fast.count == reference.count, f"{name}: count {fast.count} != {reference.count}"
    scale = max(float(np.abs(reference.A).max()), 1e-300)
    np.testing.assert_allclose(fast.A, reference.A, rtol=0, atol=rtol * scale, err_msg=name)
    diagonal, cost, count = np.diag(reference.A), max(reference.cost, 0.0), reference.count
    b_tol = rtol * np.sqrt(diagonal * cost) + residual_atol * np.sqrt(count * diagonal) + 1e-300
    assert np.all(np.abs(fast.b - reference.b) <= b_tol), (name, fast.b, reference.b, b_tol)
    cost_tol = rtol * cost + 2 * residual_atol * np.sqrt(count * cost) + 1e-300
    assert abs(fast.cost - reference.cost) <= cost_tol, (name, fast.cost, reference.cost)


def sorted_columns(*arrays: np.ndarray, key: np.ndarray) -> list[np.ndarray]:
    order = np.argsort(key, kind="stable")
    return [np.take(host(a), order, axis=-1) for a in arrays]


def column_key(columns: np.ndarray) -> np.ndarray:
    """A sort key of (3, N) float columns (lexicographic on x, y, z)."""
    return np.lexsort(columns[::-1])


# ----------------------------------------------------------------------------------------------
# ICP


def check_icp_system(impl: SimpleNamespace, width: int, height: int) -> None:
    camera, previous, current, _, frame, model = room(width, height)
    level = frame.levels[0]
    for index, pose in enumerate(poses_to_try(previous, current)):
        args = (level.vertices, level.normals, pose, *model[0], previous, camera)
        reference = ref_icp.icp_system(*args)
        assert reference.count > 0.3 * width * height  # the test sees real pairs
        assert_systems_close(f"icp_system pose {index}", impl.icp_system(*args), reference)
    if QUICK:
        return
    # Non-default thresholds reach the kernel (a tight 1 cm / 5 deg rejects most pairs here).
    args = (level.vertices, level.normals, current, *model[0], previous, camera, 0.01, 5.0)
    assert_systems_close("icp_system tight", impl.icp_system(*args), ref_icp.icp_system(*args))


def check_icp_system_robust(impl: SimpleNamespace, width: int, height: int) -> None:
    """Huber and Tukey rows (icp.robust_kernel) at an estimate ~1 cm off, with a 2 mm noise
    scale so that both branches of each kernel are taken by many pairs, then each kernel with
    the depth noise weights."""
    camera, previous, current, _, frame, model = room(width, height)
    level = frame.levels[0]
    pose = poses_to_try(previous, current)[-1]
    # A hole in the model (no surface raycast there): its points are rejected, and their NaN
    # rows must not reach the weighted sums.
    model_vertices, model_normals = model[0][0].copy(), model[0][1].copy()
    model_vertices[: height // 3, : width // 3] = np.nan
    model_normals[: height // 3, : width // 3] = np.nan
    model_maps = (model_vertices, model_normals)
    args = (level.vertices, level.normals, pose, *model_maps, previous, camera, 0.10, 20.0)
    points, normals = ref_icp.valid_points(level.vertices, level.normals)
    pairs = ref_icp.associate(
        points, normals, pose, *ref_icp.map_columns(*model_maps), previous, camera, 0.10, 20.0
    )
    residuals = np.abs(ref_icp.point_to_plane_rows(*pairs)[1])
    least_squares = ref_icp.icp_system(*args)
    for kernel in ("huber", "tukey"):
        threshold = ref_icp.robust_threshold(kernel, 0.002)
        beyond = float(np.mean(residuals > threshold))
        assert 0.05 < beyond < 0.95, (kernel, beyond)  # both branches are exercised
        reference = ref_icp.icp_system(*args, kernel, 0.002)
        assert not np.allclose(reference.A, least_squares.A, rtol=1e-3)  # the weights act
        fast = impl.icp_system(*args, kernel, 0.002)
        assert_systems_close(f"icp_system {kernel}", fast, reference)
    # Depth noise weights (icp.pair_weights) on each kernel, least squares included: the room's
    # depths span metres, so the pairs' weights differ by an order of magnitude.
    for kernel in ("none", "huber", "tukey"):
        unweighted = ref_icp.icp_system(*args, kernel, 0.002)
        reference = ref_icp.icp_system(*args, kernel, 0.002, 0.0034)
        assert not np.allclose(reference.A, unweighted.A, rtol=1e-3)
        fast = impl.icp_system(*args, kernel, 0.002, 0.0034)
        assert_systems_close(f"icp_system {kernel} depth noise", fast, reference)


def check_associate_and_rows(impl: SimpleNamespace, width: int, height: int) -> None:
    camera, previous, current, _, frame, model = room(width, height)
    level = frame.levels[0]
    points, normals = ref_icp.valid_points(level.vertices, level.normals)
    columns = ref_icp.map_columns(*model[0])
    pose = poses_to_try(previous, current)[-1]
    args = (points, normals, pose, *columns, previous, camera, 0.10, 20.0)
    reference = ref_icp.associate(*args)
    fast = [host(a) for a in impl.associate(*args)]
    assert fast[0].shape == reference[0].shape
    key_fast, key_ref = column_key(fast[0]), column_key(reference[0])
    for got, want in zip(fast, reference, strict=True):
        np.testing.assert_allclose(got[:, key_fast], want[:, key_ref], rtol=0, atol=ROW_ATOL)
    jacobian, residuals = impl.point_to_plane_rows(*reference)
    ref_jacobian, ref_residuals = ref_icp.point_to_plane_rows(*reference)
    np.testing.assert_allclose(host(jacobian), ref_jacobian, rtol=0, atol=ROW_ATOL)
    np.testing.assert_allclose(host(residuals), ref_residuals, rtol=0, atol=ROW_ATOL)


def check_accumulate(impl: SimpleNamespace, count: int) -> None:
    rng = np.random.default_rng(count)
    jacobian = rng.normal(size=(6, count)) * [[1], [2], [3], [0.1], [10], [1]]
    residuals = rng.normal(size=count)
    weights = rng.uniform(0.1, 2.0, count)
    for w in (None, weights):
        fast = impl.accumulate(jacobian, residuals, w)
        assert_systems_close(
            f"accumulate {count}", fast, ref_solve.accumulate(jacobian, residuals, w)
        )
    empty = impl.accumulate(np.zeros((6, 0)), np.zeros(0))
    assert empty.count == 0 and not empty.A.any() and not empty.b.any() and empty.cost == 0


# ----------------------------------------------------------------------------------------------
# RGB-D


def level_inputs(width: int, height: int, which: str = "current", level: int = 0):
    camera, previous, current, previous_frame, current_frame, _ = room(width, height)
    frame = current_frame if which == "current" else previous_frame
    data = frame.levels[level]
    return data, camera.at_level(level)


def check_interest_points(impl: SimpleNamespace, width: int, height: int) -> None:
    data, camera = level_inputs(width, height)
    for threshold in (5.0,) if QUICK else (12.0, 3.0):
        got = np.sort(host(impl.interest_points(data.intensity_dx, data.intensity_dy, threshold)))
        want = ref_rgbd.interest_points(data.intensity_dx, data.intensity_dy, threshold)
        assert 0 < len(want) < width * height
        np.testing.assert_array_equal(got, want)
    # Exactly at the threshold (3^2 + 4^2 = 5^2 in float32 and float64): kept, as the reference.
    dx = np.zeros((height, width), np.float32)
    dy = np.zeros((height, width), np.float32)
    dx[1, 2], dy[1, 2] = 3.0, 4.0
    dx[2, 3], dy[2, 3] = 3.0, 3.99
    got = np.sort(host(impl.interest_points(dx, dy, 5.0)))
    np.testing.assert_array_equal(got, ref_rgbd.interest_points(dx, dy, 5.0))
    assert list(got) == [1 * width + 2]


def prepared(impl: SimpleNamespace, width: int, height: int, threshold: float = 5.0):
    """(fast, reference) InterestPoints of the current frame's level 0, the fast one sorted."""
    data, camera = level_inputs(width, height)
    args = (
        data.depth,
        data.intensity,
        data.intensity_dx,
        data.intensity_dy,
        camera,
        threshold,
        6.0,
    )
    fast = impl.prepare_level(*args)
    reference = ref_rgbd.prepare_level(*args)
    indices, points, intensity, gradient = sorted_columns(
        fast.indices, fast.points, fast.intensity, fast.gradient, key=host(fast.indices)
    )
    return ref_rgbd.InterestPoints(indices, points, intensity, gradient), reference


def check_prepare_level(impl: SimpleNamespace, width: int, height: int) -> None:
    fast, reference = prepared(impl, width, height)
    assert len(reference.indices) > 0.1 * width * height
    np.testing.assert_array_equal(fast.indices, reference.indices)
    np.testing.assert_allclose(fast.points, reference.points, rtol=0, atol=ROW_ATOL)
    np.testing.assert_array_equal(fast.intensity, reference.intensity)
    np.testing.assert_array_equal(fast.gradient, reference.gradient)


def check_correspond_and_rows(impl: SimpleNamespace, width: int, height: int) -> None:
    camera, previous, current, previous_frame, _, _ = room(width, height)
    points, _ = prepared(impl, width, height)
    prev = previous_frame.levels[0]
    for index, pose in enumerate(poses_to_try(previous, current)):
        for warped in (True,) if QUICK else (False, True):
            gradients = (prev.intensity_dx, prev.intensity_dy) if warped else (None, None)
            args = (points, pose, previous, prev.depth, prev.intensity, camera, 0.07, *gradients)
            reference = ref_rgbd.correspond(*args)
            fast = impl.correspond(*args)
            name = f"correspond pose {index} warped {warped}"
            assert len(reference.kept) > 0.05 * width * height, name
            kept, world, warp, residuals, gradient = sorted_columns(
                fast.kept, fast.world, fast.warped, fast.residuals, fast.gradient,
                key=host(fast.kept),
            )  # fmt: skip
            np.testing.assert_array_equal(kept, reference.kept, err_msg=name)
            for got, want, atol in (
                (world, reference.world, ROW_ATOL),
                (warp, reference.warped, ROW_ATOL),
                (residuals, reference.residuals, INTENSITY_ATOL),
                (gradient, reference.gradient, INTENSITY_ATOL),  # sampled in "warped" mode
            ):
                np.testing.assert_allclose(got, want, rtol=0, atol=atol, err_msg=name)
            jacobian, _ = impl.photometric_rows(reference, previous, camera)
            ref_jacobian, _ = ref_rgbd.photometric_rows(reference, previous, camera)
            np.testing.assert_allclose(
                host(jacobian), ref_jacobian, rtol=ROW_RTOL, atol=ROW_ATOL, err_msg=name
            )
            assert_systems_close(
                f"rgbd_system pose {index} warped {warped}",
                impl.rgbd_system(*args),
                ref_rgbd.rgbd_system(*args),
                residual_atol=INTENSITY_ATOL,
            )


def check_joint_system(impl: SimpleNamespace, width: int, height: int) -> None:
    """The joint system of the fast ICP and RGB-D systems equals the reference chain's."""
    camera, previous, current, previous_frame, frame, model = room(width, height)
    points, ref_points = prepared(impl, width, height)
    prev, level = previous_frame.levels[0], frame.levels[0]
    pose = poses_to_try(previous, current)[-1]
    icp_args = (level.vertices, level.normals, pose, *model[0], previous, camera)
    rgbd_args = (pose, previous, prev.depth, prev.intensity, camera)
    fast_icp, fast_rgbd = impl.icp_system(*icp_args), impl.rgbd_system(points, *rgbd_args)
    ref_icp_system = ref_icp.icp_system(*icp_args)
    ref_rgbd_system = ref_rgbd.rgbd_system(ref_points, *rgbd_args)
    for weighting in ref_combined.WEIGHTINGS:
        assert_systems_close(
            f"joint_system {weighting}",
            impl.joint_system(fast_icp, fast_rgbd, 0.1, weighting),
            ref_combined.joint_system(ref_icp_system, ref_rgbd_system, 0.1, weighting),
            residual_atol=INTENSITY_ATOL,
        )


# ----------------------------------------------------------------------------------------------
# Degenerate inputs


def check_zero_depth(impl: SimpleNamespace, width: int, height: int) -> None:
    """No depth anywhere: empty lists, empty systems, and solve refuses them."""
    camera, previous, current, previous_frame, frame, model = room(width, height)
    data = frame.levels[0]
    zero = np.zeros_like(data.depth)
    points = impl.prepare_level(zero, data.intensity, data.intensity_dx, data.intensity_dy,
                                camera, 5.0, 6.0)  # fmt: skip
    assert host(points.indices).shape == (0,) and host(points.points).shape == (3, 0)
    prev = previous_frame.levels[0]
    real_points = None if QUICK else prepared(impl, width, height)[0]
    cases = [("no current depth", points, prev.depth), ("no previous depth", real_points, zero)]
    for name, pts, depth in cases[:1] if QUICK else cases:
        args = (pts, current, previous, depth, prev.intensity, camera, 0.07)
        system = impl.rgbd_system(*args)
        assert system.count == 0 and not system.A.any() and system.cost == 0, name
        assert len(host(impl.correspond(*args).kept)) == 0, name
        xi, reason = impl.solve(system, 6)
        assert xi is None and "too few correspondences (0 < 6)" in reason
    nan = np.full_like(data.vertices, np.nan)
    system = impl.icp_system(nan, nan, current, *model[0], previous, camera)
    assert system.count == 0 and not system.A.any()
    if QUICK:
        return
    system = impl.icp_system(data.vertices, data.normals, current, nan, nan, previous, camera)
    assert system.count == 0 and not system.A.any()


def check_empty_frustum(impl: SimpleNamespace, width: int, height: int) -> None:
    """The current estimate turned away from everything the model / previous frame saw."""
    camera, previous, current, previous_frame, frame, model = room(width, height)
    away = current @ se3.exp(np.array([0.0, np.pi, 0.0, 0.0, 0.0, 0.0]))  # facing backwards
    level = frame.levels[0]
    system = impl.icp_system(level.vertices, level.normals, away, *model[0], previous, camera)
    assert system.count == ref_icp.icp_system(
        level.vertices, level.normals, away, *model[0], previous, camera
    ).count == 0  # fmt: skip
    points, _ = prepared(impl, width, height)
    prev = previous_frame.levels[0]
    args = (points, away, previous, prev.depth, prev.intensity, camera, 0.07)
    assert impl.rgbd_system(*args).count == 0 == ref_rgbd.rgbd_system(*args).count
    if not QUICK:
        assert len(host(impl.correspond(*args).kept)) == 0


def border_camera(width: int, height: int) -> Intrinsics:
    # fx = fy = 64 and c = (size - 1) / 2 + 0.5 steps: projections of the points below are exact.
    return Intrinsics(64.0, 64.0, (width - 1) / 2, (height - 1) / 2, width, height)


def check_borders(impl: SimpleNamespace, width: int, height: int) -> None:
    """Points projecting exactly onto the image edges, half a pixel off, and just outside."""
    camera = border_camera(width, height)
    targets_u = [0.0, width - 1.0, -1e-9, width - 1 + 1e-9, -0.5, 0.5, width - 1.5, width - 0.5]
    targets_v = [0.0, height - 1.0, -1e-9, height - 1 + 1e-9, -0.5, height - 0.5]
    us, vs = np.meshgrid(targets_u, targets_v)
    us, vs = us.ravel(), vs.ravel()
    z = 1.0
    points = np.stack([(us - camera.cx) / camera.fx * z, (vs - camera.cy) / camera.fy * z,
                       np.full(us.shape, z)])  # fmt: skip
    # ICP: a flat model at z = 1 facing the camera everywhere; identity poses.
    model_vertices = camera.backproject(np.ones((height, width), np.float32)).astype(np.float32)
    model_normals = np.zeros((height, width, 3), np.float32)
    model_normals[..., 2] = -1.0
    normals = np.tile([[0.0], [0.0], [-1.0]], (1, points.shape[1]))
    columns = ref_icp.map_columns(model_vertices, model_normals)
    args = (points, normals, np.eye(4), *columns, np.eye(4), camera, 0.1, 20.0)
    reference = ref_icp.associate(*args)
    fast = host(impl.associate(*args)[0])
    # rint: -0.5 -> -0 (inside), width - 0.5 -> even neighbour; the sets must agree exactly.
    assert 0 < reference[0].shape[1] < points.shape[1]
    np.testing.assert_array_equal(
        fast[:, column_key(fast)], reference[0][:, column_key(reference[0])]
    )
    # RGB-D: the same points as interest points of a frame, previous depth 1 everywhere.
    rng = np.random.default_rng(5)
    intensity = rng.uniform(0, 255, (height, width)).astype(np.float32)
    interest = ref_rgbd.InterestPoints(
        np.arange(points.shape[1]), points, rng.uniform(0, 255, points.shape[1]),
        rng.normal(size=(2, points.shape[1])),
    )  # fmt: skip
    depth = np.ones((height, width), np.float32)
    args = (interest, np.eye(4), np.eye(4), depth, intensity, camera, 0.07)
    reference = ref_rgbd.correspond(*args)
    fast = impl.correspond(*args)
    order = np.argsort(host(fast.kept))
    np.testing.assert_array_equal(host(fast.kept)[order], reference.kept)
    assert 0 < len(reference.kept) < points.shape[1]
    np.testing.assert_allclose(
        host(fast.residuals)[order], reference.residuals, rtol=0, atol=INTENSITY_ATOL
    )
    assert_systems_close(
        "rgbd_system at the borders",
        impl.rgbd_system(*args),
        ref_rgbd.rgbd_system(*args),
        residual_atol=INTENSITY_ATOL,
    )


# ----------------------------------------------------------------------------------------------
# Trackers


class Model:
    """The fields of raycast.ModelPrediction the trackers read."""

    def __init__(self, pose: np.ndarray, vertices: np.ndarray, normals: np.ndarray) -> None:
        self.pose, self.vertices, self.normals = pose, vertices, normals


# The checks of one pyramid level that both targets' tests run at each of their sizes.
LEVEL_CHECKS = [
    check_icp_system,
    check_icp_system_robust,
    check_associate_and_rows,
    check_interest_points,
    check_prepare_level,
    check_correspond_and_rows,
    check_joint_system,
    check_zero_depth,
    check_empty_frustum,
    check_borders,
]


def check_id(check: Callable) -> str:
    """A check's test id: its name without "check_"."""
    return check.__name__.removeprefix("check_")


def pose_difference(a: np.ndarray, b: np.ndarray) -> tuple[float, float]:
    """(metres, radians) between two poses."""
    difference = se3.inverse(a) @ b
    return float(np.linalg.norm(difference[:3, 3])), float(se3.rotation_angle(difference[:3, :3]))


def iterations_config(iterations: tuple[int, ...] | None) -> Config:
    """The default config, or every dense estimator with the given iterations per level."""
    if iterations is None:
        return Config()
    keys = ("icp.iterations", "rgbd.iterations", "rgbd.combined_iterations")
    return with_overrides(Config(), dict.fromkeys(keys, tuple(iterations)))


def check_tracker(
    make_tracker,
    method: str,
    width: int,
    height: int,
    iterations,
    tolerance: tuple[float, float],
    overrides: dict | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """The fast tracker's result equals the reference tracker's: same ok / reason / used, poses
    within `tolerance` (metres, radians). `overrides`: configuration values on top of the
    iterations. Returns (reference pose, true pose)."""
    camera, previous, current, previous_frame, frame, _ = room(width, height, 4)
    vertices, normals = scene.model(previous, camera, 1)[0]
    model = Model(previous, vertices, normals)
    config = with_overrides(iterations_config(iterations), overrides or {})
    fast = make_tracker(method, config, camera).track(previous_frame, frame, model, previous)
    reference = ref_make_tracker(method, config, camera).track(
        previous_frame, frame, model, previous
    )
    assert (fast.ok, fast.reason, fast.used) == (reference.ok, reference.reason, reference.used)
    metres, radians = pose_difference(fast.pose, reference.pose)
    assert metres <= tolerance[0] and radians <= tolerance[1], (method, iterations, metres, radians)
    return reference.pose, current
