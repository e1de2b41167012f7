"""Per-pair maths of kintinuous_ref.odometry.rgbd, written once for the CPU and CUDA targets.

`build_ops(jit, geometry)` (the pattern of kintinuous_fast.targets) defines the scalar functions
of one interest point - Algorithm 1's tests, its 3D point, its warp into the previous frame
(Algorithm 2), its photometric row and robust weight - compiled with the decorator it is given,
over the rigid transforms of `geometry` (odometry/ops.py compiled for the same target):
`numba.njit(cache=True, inline="always")` for the loops of rgbd/cpu.py, `cuda.jit(device=True)`
for the kernels of rgbd/cuda.py. Precision and order of operations: odometry/ops.py.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from types import SimpleNamespace
from typing import Any

from kintinuous_ref.odometry.rgbd import BORDER_SLACK


def build_ops(jit: Callable[[Any], Any], geometry: SimpleNamespace) -> SimpleNamespace:
    """The scalar functions of one RGB-D interest point compiled with `jit`, over `geometry`'s
    rint, transform and rotate (compiled with the same `jit`)."""
    return SimpleNamespace(
        **vars(_interest(jit)), **vars(_warps(jit, geometry)), **vars(_rows(jit, geometry))
    )


def _interest(jit: Callable[[Any], Any]) -> SimpleNamespace:
    """Algorithm 1's tests and the 3D point of an interest point (ref prepare_level)."""

    @jit
    def is_interest(dx: Any, dy: Any, v: int, u: int, g2: float) -> bool:
        """Algorithm 1's test dI/dx^2 + dI/dy^2 >= g^2, in float64 like the reference."""
        gx = float(dx[v, u])
        gy = float(dy[v, u])
        return gx * gx + gy * gy >= g2

    @jit
    def has_depth(depth: Any, v: int, u: int, max_depth: float) -> bool:
        """prepare_level's depth test: 0 < z <= max_depth and finite."""
        z = float(depth[v, u])
        return z > 0 and z <= max_depth and math.isfinite(z)

    @jit
    def backproject(u: int, v: int, z: float, camera: tuple) -> tuple[float, float, float]:
        """X = z K^-1 (u, v, 1) as prepare_level computes it, `camera` = (fx, fy, cx, cy)."""
        fx, fy, cx, cy = camera
        return (u - cx) * z / fx, (v - cy) * z / fy, z

    return SimpleNamespace(is_interest=is_interest, has_depth=has_depth, backproject=backproject)


def _warps(jit: Callable[[Any], Any], geometry: SimpleNamespace) -> SimpleNamespace:
    """Algorithm 2 for one interest point (ref `correspond`)."""

    rint, transform = geometry.rint, geometry.transform

    @jit
    def sample_bilinear(image: Any, u: float, v: float) -> float:
        """Bilinear interpolation at (u, v) inside [0, w-1] x [0, h-1] (ref sample_bilinear)."""
        height = image.shape[0]
        width = image.shape[1]
        u0 = min(max(int(math.floor(u)), 0), width - 2)
        v0 = min(max(int(math.floor(v)), 0), height - 2)
        a = u - u0
        b = v - v0
        top = float(image[v0, u0]) * (1 - a) + float(image[v0, u0 + 1]) * a
        bottom = float(image[v0 + 1, u0]) * (1 - a) + float(image[v0 + 1, u0 + 1]) * a
        return top * (1 - b) + bottom * b

    @jit
    def warp_project(
        relative: Any, point: tuple, camera: tuple
    ) -> tuple[float, float, float, float, float]:
        """The first half of warp_point: X' = T_rel X and its projection (u, v) by `camera` =
        (fx, fy, cx, cy); (u, v) only mean something where z' > 1e-6. No branch on the data, so
        that a loop of these vectorises."""
        fx, fy, cx, cy = camera
        x, y, z = transform(relative, point[0], point[1], point[2])
        safe_z = z if z > 1e-6 else 1.0
        return x, y, z, fx * x / safe_z + cx, fy * y / safe_z + cy

    @jit
    def warp_sample(
        points: Any,
        intensity: Any,
        gradient: Any,
        k: int,
        warp: tuple,
        pose: Any,
        previous_depth: Any,
        previous_intensity: Any,
        previous_dx: Any,
        previous_dy: Any,
        warped_gradient: bool,
        max_depth_change: float,
    ) -> tuple[bool, float, float, float, float, float, float, float, float, float]:
        """The second half of warp_point, from warp_project's `warp` = (x, y, z, u, v) of point
        k."""
        x, y, z, u, v = warp
        height = previous_depth.shape[0]
        width = previous_depth.shape[1]
        nan = math.nan
        if not z > 1e-6:
            return False, nan, nan, nan, nan, nan, nan, nan, nan, nan
        slack = BORDER_SLACK  # the reference's rounding slack at the border pixel centres
        if not (u >= -slack and u <= width - 1 + slack and v >= -slack and v <= height - 1 + slack):
            return False, nan, nan, nan, nan, nan, nan, nan, nan, nan
        d = float(previous_depth[int(rint(v)), int(rint(u))])
        if not (d > 0 and abs(z - d) < max_depth_change):
            return False, nan, nan, nan, nan, nan, nan, nan, nan, nan
        r = sample_bilinear(previous_intensity, u, v) - intensity[k]
        if warped_gradient:
            gx = sample_bilinear(previous_dx, u, v)
            gy = sample_bilinear(previous_dy, u, v)
        else:
            gx = gradient[0, k]
            gy = gradient[1, k]
        wx, wy, wz = transform(pose, points[0, k], points[1, k], points[2, k])
        return True, r, wx, wy, wz, x, y, z, gx, gy

    @jit
    def warp_point(
        points: Any,
        intensity: Any,
        gradient: Any,
        k: int,
        relative: Any,
        pose: Any,
        previous_depth: Any,
        previous_intensity: Any,
        previous_dx: Any,
        previous_dy: Any,
        warped_gradient: bool,
        camera: tuple,
        max_depth_change: float,
    ) -> tuple[bool, float, float, float, float, float, float, float, float, float]:
        """Algorithm 2 for interest point k (ref `correspond`): (kept, r = I_n(p') - I_{n+1}(p),
        world p = T X, warped X' = T_rel X, gradient used in J). Kept when p' lies inside the
        image (room for the 2x2 bilinear neighbourhood) and the previous depth at the nearest
        pixel agrees with z' to within d_s. warp_project then warp_sample (the CPU runs the
        first half of a block of points in a loop that vectorises)."""
        warp = warp_project(relative, (points[0, k], points[1, k], points[2, k]), camera)
        return warp_sample(
            points,
            intensity,
            gradient,
            k,
            warp,
            pose,
            previous_depth,
            previous_intensity,
            previous_dx,
            previous_dy,
            warped_gradient,
            max_depth_change,
        )

    return SimpleNamespace(
        sample_bilinear=sample_bilinear,
        warp_project=warp_project,
        warp_sample=warp_sample,
        warp_point=warp_point,
    )


def _rows(jit: Callable[[Any], Any], geometry: SimpleNamespace) -> SimpleNamespace:
    """One pair's photometric row and robust weight (ref photometric_rows, robust_row_weights)."""

    rotate = geometry.rotate

    @jit
    def photometric_row(
        world: tuple, warped: tuple, gradient: tuple, previous_pose: Any, focal: tuple
    ) -> tuple[float, float, float, float, float, float]:
        """J of one intensity difference (ref photometric_rows): a = grad I . dpi/dX', turned
        into the world frame c = R_prev a, J = [p x c, c]; p = `world`, X' = `warped` (x, y, z),
        grad I = `gradient` (gx, gy), `focal` = (fx, fy)."""
        wx, wy, wz = world
        x, y, z = warped
        gx, gy = gradient
        fx, fy = focal
        a0 = gx * fx / z
        a1 = gy * fy / z
        a2 = -(gx * fx * x + gy * fy * y) / (z * z)
        c0, c1, c2 = rotate(previous_pose, a0, a1, a2)
        return wy * c2 - wz * c1, wz * c0 - wx * c2, wx * c1 - wy * c0, c0, c1, c2

    @jit
    def robust_weight(r: float, sigma: float) -> float:
        """w_k = 1 / (sigma' + |r_k|), 1 where that is 0 (ref robust_row_weights)."""
        denominator = sigma + abs(r)
        safe = denominator if denominator > 1e-12 else 1.0  # a select: the CPU's loop vectorises
        return 1.0 / safe

    return SimpleNamespace(photometric_row=photometric_row, robust_weight=robust_weight)
