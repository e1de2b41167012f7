"""Per-correspondence maths of kintinuous_ref.odometry, written once for the CPU and CUDA targets.

`build_ops(jit)` (the pattern of kintinuous_fast.targets) defines scalar functions - transform a
point, round a projection, associate one ICP point, warp one RGB-D interest point, build one
Jacobian row, add one row to the normal equations - compiled with the decorator it is given:
`numba.njit(cache=True)` for the loops of odometry/cpu.py, `cuda.jit(device=True)` for the
kernels of odometry/cuda.py.

Precision: the reference computes every per-correspondence quantity in float64 (its maps are
float32, converted once); so do these functions (values read from arrays go through float()).
Each formula is written in the reference's order of operations, so the rows agree to the last bit
up to FMA contraction and the order of the 3-term dot products inside NumPy's matrix products
(~1 ulp). Only the sums over all rows differ in order (chunked partials here, BLAS in the
reference): relative differences ~1e-15 of the largest terms.

The normal equations travel as a vector of NV float64 values per thread / chunk / block:
21 upper-triangle entries of A (row-major, i <= j), 6 entries of b, the cost r^T W r, the count
of rows and one spare slot (the ICP kernels count the valid current points there, which the
inlier fraction needs). The host sums the partials in float64 and unpacks them (odometry/host.py).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from types import SimpleNamespace
from typing import Any

from kintinuous_fast.targets import build_rint
from kintinuous_ref.camera import AXIAL_NOISE_BASE, AXIAL_NOISE_GROWTH, AXIAL_NOISE_NEAREST
from kintinuous_ref.odometry.icp import ROBUST_KERNELS
from kintinuous_ref.odometry.rgbd import BORDER_SLACK

# The ICP robust kernels as the integer codes the kernels take (index into ROBUST_KERNELS).
KERNEL_NONE, KERNEL_HUBER, KERNEL_TUKEY = (ROBUST_KERNELS.index(name) for name in ROBUST_KERNELS)

# Slots of the accumulated vector (see the module docstring).
NV = 30
SLOT_B = 21
SLOT_COST = 27
SLOT_COUNT = 28
SLOT_EXTRA = 29


def build_ops(jit: Callable[[Any], Any]) -> SimpleNamespace:
    """The scalar functions of dense odometry compiled with `jit` (see kintinuous_fast.targets)."""

    rint = build_rint(jit)[0]

    @jit
    def transform(m: Any, x: float, y: float, z: float) -> tuple[float, float, float]:
        """The rigid transform of the 4x4 (or 3x4) float64 matrix m applied to (x, y, z)."""
        return (
            m[0, 0] * x + m[0, 1] * y + m[0, 2] * z + m[0, 3],
            m[1, 0] * x + m[1, 1] * y + m[1, 2] * z + m[1, 3],
            m[2, 0] * x + m[2, 1] * y + m[2, 2] * z + m[2, 3],
        )

    @jit
    def rotate(m: Any, x: float, y: float, z: float) -> tuple[float, float, float]:
        """The rotation part of m applied to (x, y, z)."""
        return (
            m[0, 0] * x + m[0, 1] * y + m[0, 2] * z,
            m[1, 0] * x + m[1, 1] * y + m[1, 2] * z,
            m[2, 0] * x + m[2, 1] * y + m[2, 2] * z,
        )

    # ------------------------------------------------------------------------------------------
    # ICP (kintinuous_ref.odometry.icp)

    @jit
    def project_nearest(m: Any, point: tuple, camera: tuple, size: tuple) -> tuple[int, int]:
        """(row, column) of the pixel nearest to m `point` in a camera `camera` = (fx, fy, cx,
        cy) of `size` = (width, height), (-1, -1) behind the camera or outside the image (ref
        `associate`). No branch on the data (NaN fails every test), so that a loop of these
        vectorises."""
        fx, fy, cx, cy = camera
        width, height = size
        mx, my, mz = transform(m, point[0], point[1], point[2])
        front = mz > 1e-6
        safe_z = mz if front else 1.0
        u = rint(fx * mx / safe_z + cx)
        v = rint(fy * my / safe_z + cy)
        inside = front & (u >= 0) & (u < width) & (v >= 0) & (v < height)
        return (int(v) if inside else -1), (int(u) if inside else -1)

    @jit
    def is_compatible(w: tuple, g: tuple, q: tuple, u: tuple, limits: tuple) -> bool:
        """The ICP pair tests of a world point w with normal g against a model vertex q with
        normal u (each (x, y, z)): at most the distance threshold apart, normals within the
        angle threshold, `limits` = (squared distance, cos angle) (NaN fails both)."""
        dist2, cos_min = limits
        dx = w[0] - q[0]
        dy = w[1] - q[1]
        dz = w[2] - q[2]
        squared = dx * dx + dy * dy + dz * dz
        cos_angle = g[0] * u[0] + g[1] * u[1] + g[2] * u[2]
        return (squared <= dist2) & (cos_angle >= cos_min)

    @jit
    def match_pixel(
        point: tuple,
        normal: tuple,
        pose: Any,
        model_vertices: Any,
        model_normals: Any,
        pixel: tuple,
        limits: tuple,
    ) -> tuple[bool, float, float, float, float, float, float, float, float, float]:
        """The ICP pair of one valid current point (`point`, `normal`) and the model `pixel` =
        (iv, iu) it projects to: (kept, world point p = T v, model vertex, model normal).
        Rejected without a model surface there (NaN fails both tests), farther than the distance
        threshold or with normals more than the angle threshold apart (is_compatible's
        `limits`)."""
        iv, iu = pixel
        wx, wy, wz = transform(pose, point[0], point[1], point[2])
        qx = float(model_vertices[iv, iu, 0])
        qy = float(model_vertices[iv, iu, 1])
        qz = float(model_vertices[iv, iu, 2])
        ux = float(model_normals[iv, iu, 0])
        uy = float(model_normals[iv, iu, 1])
        uz = float(model_normals[iv, iu, 2])
        g = rotate(pose, normal[0], normal[1], normal[2])
        if is_compatible((wx, wy, wz), g, (qx, qy, qz), (ux, uy, uz), limits):
            return True, wx, wy, wz, qx, qy, qz, ux, uy, uz
        nan = math.nan
        return False, nan, nan, nan, nan, nan, nan, nan, nan, nan

    @jit
    def icp_match(
        point: tuple,
        normal: tuple,
        pose: Any,
        to_model: Any,
        model_vertices: Any,
        model_normals: Any,
        camera: tuple,
        limits: tuple,
    ) -> tuple[bool, float, float, float, float, float, float, float, float, float]:
        """Projective association of one valid current point (ref `associate`): the nearest pixel
        of the model's camera (project_nearest), then the tests of match_pixel."""
        size = (model_vertices.shape[1], model_vertices.shape[0])
        pixel = project_nearest(to_model, point, camera, size)
        if pixel[0] < 0:
            nan = math.nan
            return False, nan, nan, nan, nan, nan, nan, nan, nan, nan
        return match_pixel(point, normal, pose, model_vertices, model_normals, pixel, limits)

    @jit
    def map_point(vertices: Any, normals: Any, v: int, u: int) -> tuple[bool, float, ...]:
        """The current vertex and normal at (v, u) in float64; False where any is NaN/inf
        (ref `valid_points`)."""
        px = float(vertices[v, u, 0])
        py = float(vertices[v, u, 1])
        pz = float(vertices[v, u, 2])
        nx = float(normals[v, u, 0])
        ny = float(normals[v, u, 1])
        nz = float(normals[v, u, 2])
        ok = (  # & (not `and`): one branch per point instead of six
            math.isfinite(px)
            & math.isfinite(py)
            & math.isfinite(pz)
            & math.isfinite(nx)
            & math.isfinite(ny)
            & math.isfinite(nz)
        )
        return ok, px, py, pz, nx, ny, nz

    @jit
    def point_to_plane_row(
        world: tuple, vertex: tuple, normal: tuple
    ) -> tuple[float, float, float, float, float, float, float]:
        """J = [p x n_m, n_m] and r = (p - v_m) . n_m of one pair (eq. 9): (j0..j5, r), p =
        `world`, v_m = `vertex`, n_m = `normal` (x, y, z)."""
        wx, wy, wz = world
        qx, qy, qz = vertex
        ux, uy, uz = normal
        r = (wx - qx) * ux + (wy - qy) * uy + (wz - qz) * uz
        return wy * uz - wz * uy, wz * ux - wx * uz, wx * uy - wy * ux, ux, uy, uz, r

    @jit
    def robust_icp_weight(r: float, kernel: int, threshold: float) -> float:
        """The IRLS weight of a point-to-plane residual (ref icp.robust_weights): 1 for
        KERNEL_NONE; Huber: 1 inside k = threshold, k / |r| beyond; Tukey: (1 - (r / c)^2)^2
        inside c = threshold, 0 beyond. Selects, no data branches: the CPU's loop vectorises."""
        magnitude = abs(r)
        huber = 1.0 if magnitude <= threshold else threshold / max(magnitude, 1e-300)
        ratio = r / threshold if threshold > 0 else 0.0
        inside = 1.0 - ratio * ratio
        tukey = inside * inside if magnitude < threshold else 0.0
        weight = huber if kernel == KERNEL_HUBER else 1.0
        return tukey if kernel == KERNEL_TUKEY else weight

    @jit
    def weighs_pairs(robust: tuple) -> bool:
        """Whether host.robust_terms give the pairs weights other than 1 (else least squares)."""
        return robust[0] != KERNEL_NONE or robust[2] >= 0

    @jit
    def pair_weight(r: float, z: float, robust: tuple) -> float:
        """A pair's weight in the normal equations (ref icp.pair_weights) for a current point at
        depth z: `robust` = (kernel code, threshold, model variance, reference variance), the
        last two host.robust_terms'. The robust weight of s r times s^2, s^2 = reference /
        (axial_noise(z)^2 + model variance); s = 1 where the model variance is negative (no
        depth noise weights)."""
        kernel, threshold, model_variance, reference_variance = robust
        offset = z - AXIAL_NOISE_NEAREST
        axial = AXIAL_NOISE_BASE + AXIAL_NOISE_GROWTH * (offset * offset)
        ratio = reference_variance / (axial * axial + model_variance)
        scale = math.sqrt(ratio) if model_variance >= 0 else 1.0
        return robust_icp_weight(scale * r, kernel, threshold) * (scale * scale)

    # ------------------------------------------------------------------------------------------
    # RGB-D (kintinuous_ref.odometry.rgbd)

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

    # ------------------------------------------------------------------------------------------
    # Normal equations

    @jit
    def add_row(acc: Any, jacobian: tuple, r: float, w: float) -> None:
        """acc += w [J^T J (upper triangle), J^T r, r^2, 1] for one row (ref accumulate), J =
        `jacobian` (j0..j5)."""
        j0, j1, j2, j3, j4, j5 = jacobian
        a0 = w * j0
        a1 = w * j1
        a2 = w * j2
        a3 = w * j3
        a4 = w * j4
        a5 = w * j5
        acc[0] += a0 * j0
        acc[1] += a0 * j1
        acc[2] += a0 * j2
        acc[3] += a0 * j3
        acc[4] += a0 * j4
        acc[5] += a0 * j5
        acc[6] += a1 * j1
        acc[7] += a1 * j2
        acc[8] += a1 * j3
        acc[9] += a1 * j4
        acc[10] += a1 * j5
        acc[11] += a2 * j2
        acc[12] += a2 * j3
        acc[13] += a2 * j4
        acc[14] += a2 * j5
        acc[15] += a3 * j3
        acc[16] += a3 * j4
        acc[17] += a3 * j5
        acc[18] += a4 * j4
        acc[19] += a4 * j5
        acc[20] += a5 * j5
        acc[21] += a0 * r
        acc[22] += a1 * r
        acc[23] += a2 * r
        acc[24] += a3 * r
        acc[25] += a4 * r
        acc[26] += a5 * r
        acc[27] += w * r * r
        acc[28] += 1.0

    return SimpleNamespace(
        rint=rint,
        transform=transform,
        rotate=rotate,
        project_nearest=project_nearest,
        match_pixel=match_pixel,
        is_compatible=is_compatible,
        icp_match=icp_match,
        map_point=map_point,
        point_to_plane_row=point_to_plane_row,
        robust_icp_weight=robust_icp_weight,
        pair_weight=pair_weight,
        weighs_pairs=weighs_pairs,
        is_interest=is_interest,
        has_depth=has_depth,
        backproject=backproject,
        sample_bilinear=sample_bilinear,
        warp_project=warp_project,
        warp_sample=warp_sample,
        warp_point=warp_point,
        photometric_row=photometric_row,
        robust_weight=robust_weight,
        add_row=add_row,
    )
