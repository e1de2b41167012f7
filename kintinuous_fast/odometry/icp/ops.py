"""Per-pair maths of kintinuous_ref.odometry.icp, written once for the CPU and CUDA targets.

`build_ops(jit, geometry)` (the pattern of kintinuous_fast.targets) defines the scalar functions
of one ICP pair - round a projection to a pixel, associate one current point with the model, its
point-to-plane row, its robust and depth noise weight - compiled with the decorator it is given,
over the rigid transforms of `geometry` (odometry/ops.py compiled for the same target):
`numba.njit(cache=True, inline="always")` for the loops of icp/cpu.py, `cuda.jit(device=True)`
for the kernels of icp/cuda.py. Precision and order of operations: odometry/ops.py.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from types import SimpleNamespace
from typing import Any

from kintinuous_ref.camera import AXIAL_NOISE_BASE, AXIAL_NOISE_GROWTH, AXIAL_NOISE_NEAREST
from kintinuous_ref.vocabulary import ROBUST_KERNELS

# The ICP robust kernels as the integer codes the kernels take (index into ROBUST_KERNELS).
KERNEL_NONE, KERNEL_HUBER, KERNEL_TUKEY = (ROBUST_KERNELS.index(name) for name in ROBUST_KERNELS)


def build_ops(jit: Callable[[Any], Any], geometry: SimpleNamespace) -> SimpleNamespace:
    """The scalar functions of one ICP pair compiled with `jit`, over `geometry`'s rint,
    transform and rotate (compiled with the same `jit`)."""
    return SimpleNamespace(**vars(_association(jit, geometry)), **vars(_rows(jit)))


def _association(jit: Callable[[Any], Any], geometry: SimpleNamespace) -> SimpleNamespace:
    """Projective association of one current point with the model (ref `associate`)."""

    rint, transform, rotate = geometry.rint, geometry.transform, geometry.rotate

    @jit
    def read_pixel(vertices: Any, normals: Any, v: int, u: int) -> tuple[float, ...]:
        """(x, y, z, nx, ny, nz): the vertex and normal at pixel (v, u) of two maps, in
        float64."""
        return (
            float(vertices[v, u, 0]),
            float(vertices[v, u, 1]),
            float(vertices[v, u, 2]),
            float(normals[v, u, 0]),
            float(normals[v, u, 1]),
            float(normals[v, u, 2]),
        )

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
        qx, qy, qz, ux, uy, uz = read_pixel(model_vertices, model_normals, iv, iu)
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
        px, py, pz, nx, ny, nz = read_pixel(vertices, normals, v, u)
        ok = (  # & (not `and`): one branch per point instead of six
            math.isfinite(px)
            & math.isfinite(py)
            & math.isfinite(pz)
            & math.isfinite(nx)
            & math.isfinite(ny)
            & math.isfinite(nz)
        )
        return ok, px, py, pz, nx, ny, nz

    return SimpleNamespace(
        project_nearest=project_nearest,
        is_compatible=is_compatible,
        match_pixel=match_pixel,
        icp_match=icp_match,
        map_point=map_point,
    )


def _rows(jit: Callable[[Any], Any]) -> SimpleNamespace:
    """One pair's point-to-plane row and its weight (ref point_to_plane_rows, pair_weights)."""

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
    def store_point_to_plane(world: Any, mv: Any, mn: Any, k: int, jacobian: Any, residuals: Any):  # noqa: ANN202
        """Pair k's row (point_to_plane_row of column k of each (3, n) array) into column k of
        `jacobian` (6, n) and `residuals` (n,): one element of ref point_to_plane_rows."""
        j0, j1, j2, j3, j4, j5, r = point_to_plane_row(
            (world[0, k], world[1, k], world[2, k]),
            (mv[0, k], mv[1, k], mv[2, k]),
            (mn[0, k], mn[1, k], mn[2, k]),
        )
        jacobian[0, k], jacobian[1, k], jacobian[2, k] = j0, j1, j2
        jacobian[3, k], jacobian[4, k], jacobian[5, k] = j3, j4, j5
        residuals[k] = r

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
        """Whether icp.robust_terms give the pairs weights other than 1 (else least squares)."""
        return robust[0] != KERNEL_NONE or robust[2] >= 0

    @jit
    def pair_weight(r: float, z: float, robust: tuple) -> float:
        """A pair's weight in the normal equations (ref icp.pair_weights) for a current point at
        depth z: `robust` = (kernel code, threshold, model variance, reference variance), the
        last two icp.robust_terms'. The robust weight of s r times s^2, s^2 = reference /
        (axial_noise(z)^2 + model variance); s = 1 where the model variance is negative (no
        depth noise weights)."""
        kernel, threshold, model_variance, reference_variance = robust
        offset = z - AXIAL_NOISE_NEAREST
        axial = AXIAL_NOISE_BASE + AXIAL_NOISE_GROWTH * (offset * offset)
        ratio = reference_variance / (axial * axial + model_variance)
        scale = math.sqrt(ratio) if model_variance >= 0 else 1.0
        return robust_icp_weight(scale * r, kernel, threshold) * (scale * scale)

    return SimpleNamespace(
        point_to_plane_row=point_to_plane_row,
        store_point_to_plane=store_point_to_plane,
        robust_icp_weight=robust_icp_weight,
        weighs_pairs=weighs_pairs,
        pair_weight=pair_weight,
    )
