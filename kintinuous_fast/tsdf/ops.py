"""Per-voxel maths of TSDF and colour integration (kintinuous_ref.tsdf.integrate and
kintinuous_ref.colour), written once for the CPU and the CUDA target, on the stored voxels of
kintinuous_fast.tsdf.voxel: the arithmetic is the reference's, in the same precision and order,
with a rounding to the stored type at the end of each update.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from types import SimpleNamespace
from typing import Any

import numpy as np

from kintinuous_fast.targets import build_rint
from kintinuous_fast.tsdf import voxel as voxel_ops
from kintinuous_fast.tsdf.voxel import TSDF_MAX


def build_ops(jit: Callable[[Any], Any], voxels: SimpleNamespace | None = None) -> SimpleNamespace:
    """The integration functions compiled with `jit`, on `voxels` (tsdf.voxel.build_ops(jit)
    unless given: a caller that also samples the volume shares its functions), in one
    namespace."""
    voxels = voxels or voxel_ops.build_ops(jit)
    projection = build_projection(jit)
    fusion = _build_fusion(jit, voxels)
    columns = _build_columns(jit, voxels, projection, fusion)
    parts = (projection, fusion, columns, build_colour_weight(jit))
    return SimpleNamespace(**{name: f for part in parts for name, f in vars(part).items()})


def build_projection(jit: Callable[[Any], Any]) -> SimpleNamespace:
    """A voxel's camera-frame position, its pixel and its distance; a pixel's measured distance."""
    rint32 = build_rint(jit)[1]

    @jit
    def ray_distance_pixel(d: Any, u: int, v: int, camera: Any) -> Any:
        """lambda D: the measured distance along pixel (u, v)'s ray (float32 as the reference),
        `camera` = (fx, fy, cx, cy); -inf where D is not > 0 (no measurement), so that every sdf
        taken from it is below -mu: no update, as the reference's D > 0 test."""
        fx, fy, cx, cy = camera
        x = (u - cx) * 1.0 / fx
        y = (v - cy) * 1.0 / fy
        measured = np.float32(float(d) * math.sqrt(x * x + y * y + 1.0))
        return measured if d > 0 else np.float32(-np.inf)

    @jit
    def project_voxel(x: Any, y: Any, z: Any, intrinsics: Any, image_size: tuple) -> Any:
        """The pixel of a camera-frame voxel centre, (u, v) = round(pi(p_c)) (float32, as NumPy 2
        computes the reference's projection), as the flat index v W + u (uint32), `image_size`
        = (W, H); W H, the
        "no pixel" slot one past the image, when z <= 0 or it falls outside the image. Images
        are read flat here: ray distances (ray_distance_pixel's, H W + 1 with -inf in that
        slot), colour (H W, 3), colour weights (H W). Selects only, no branch and no
        integer-to-float conversion, so that a loop of it vectorises (the cpu integration's
        first pass)."""
        width, height = image_size
        uf = intrinsics[0] * x / z + intrinsics[2]
        vf = intrinsics[1] * y / z + intrinsics[3]
        ur = rint32(uf)  # float32: a float64 rounding costs integration far more
        vr = rint32(vf)
        zero, last_u, last_v = np.float32(0), np.float32(width - 1), np.float32(height - 1)
        inside = (z > zero) & (ur >= zero) & (ur <= last_u) & (vr >= zero) & (vr <= last_v)
        pixel = np.uint32(vr) * np.uint32(width) + np.uint32(ur)
        return pixel if inside else np.uint32(width * height)

    @jit
    def voxel_norm(x: Any, y: Any, z: Any) -> Any:
        """|p_c| in float32, in the reference's order."""
        return np.float32(math.sqrt(np.float32(np.float32(x * x) + y * y) + z * z))

    @jit
    def column_start(base: Any, steps: Any, fi: Any, fj: Any) -> tuple:
        """Camera-frame centre of voxel (i, j, 0): base + i a_x + j a_y in float32, the
        reference's order of additions (a column then adds k a_z)."""
        return (
            (base[0] + fi * steps[0, 0]) + fj * steps[1, 0],
            (base[1] + fi * steps[0, 1]) + fj * steps[1, 1],
            (base[2] + fi * steps[0, 2]) + fj * steps[1, 2],
        )

    return SimpleNamespace(
        column_start=column_start,
        project_voxel=project_voxel,
        ray_distance_pixel=ray_distance_pixel,
        rint32=rint32,
        voxel_norm=voxel_norm,
    )


def _build_fusion(jit: Callable[[Any], Any], voxels: SimpleNamespace) -> SimpleNamespace:
    """One voxel's update from the frame: the TSDF's running average and the colour's."""
    dequantise, quantise = voxels.dequantise, voxels.quantise

    @jit
    def fuse_voxel(
        tsdf_weight: Any,
        colour_volume: Any,
        voxel: tuple,
        pixel: Any,
        sdf: Any,
        limits: tuple,
        colour: Any,
        colour_weights: Any,
        fuse_colour: bool,
    ) -> int:
        """The update of the voxel in array cell `voxel` = (ci, cj, ck) projecting to flat pixel
        index `pixel` (project_voxel's), with sdf = lambda D - |p_c| (-inf without a
        measurement); `limits` = (mu, the weight cap, the colour weight cap) in float32.

        Update if sdf >= -mu: running average of min(1, sdf/mu) with weight W + 1 (capped);
        colour where |sdf| < mu and the pixel's colour weight > 0.

        Returns how the voxel's "observed and negative" state changed (+1, 0 or -1): the cpu
        backend keeps a bit mask of such voxels per fine brick for the raycast's empty-space
        skipping. Values that do not change are not written back (a saturated free-space voxel,
        F = 1 at the weight cap, stays as it is: no store, no dirty cache line).
        """
        ci, cj, ck = voxel
        truncation, max_weight, colour_max_weight = limits
        if not sdf >= -truncation:
            return 0
        q_old = tsdf_weight[ci, cj, ck, 0]
        stored_weight = tsdf_weight[ci, cj, ck, 1]
        w_old = np.float32(stored_weight)
        if q_old == TSDF_MAX and sdf >= truncation:
            # Free space seen again where F is already 1: the average (1 W + 1) / (W + 1) is 1
            # exactly (W is a small whole number) and no colour is fused beyond mu, so only W
            # moves. Most voxels of a frame take this path, without a division.
            w_new = min(w_old + np.float32(1.0), max_weight)
            if w_new != w_old:
                tsdf_weight[ci, cj, ck, 1] = w_new
            return 0
        observed = min(np.float32(1.0), np.float32(sdf / truncation))
        f_new = (dequantise(q_old) * w_old + observed) / (w_old + np.float32(1.0))
        q_new = quantise(f_new)
        w_new = min(w_old + np.float32(1.0), max_weight)
        if q_new != q_old:
            tsdf_weight[ci, cj, ck, 0] = q_new
        if w_new != w_old:
            tsdf_weight[ci, cj, ck, 1] = w_new
        change = (1 if q_new < 0 else 0) - (1 if q_old < 0 and stored_weight > 0 else 0)
        if not fuse_colour:
            return change
        w_c = colour_weights[pixel]
        if not (abs(sdf) < truncation and w_c > 0):
            return change
        cw_old = np.float32(colour_volume[ci, cj, ck, 3])
        for channel in range(3):
            rgb = np.float32(colour[pixel, channel])
            c_old = np.float32(colour_volume[ci, cj, ck, channel])
            c_new = (c_old * cw_old + rgb * w_c) / (cw_old + w_c)
            colour_volume[ci, cj, ck, channel] = min(max(round(float(c_new)), 0), 255)
        cw_new = round(float(min(cw_old + w_c, colour_max_weight)))
        colour_volume[ci, cj, ck, 3] = min(max(cw_new, 1), 255)
        return change

    return SimpleNamespace(fuse_voxel=fuse_voxel)


def _build_columns(
    jit: Callable[[Any], Any],
    voxels: SimpleNamespace,
    projection: SimpleNamespace,
    fusion: SimpleNamespace,
) -> SimpleNamespace:
    """A logical voxel's update, and the range of a voxel column a frame can update."""
    cell, column_start, fuse_voxel = voxels.cell, projection.column_start, fusion.fuse_voxel
    project_voxel, voxel_norm = projection.project_voxel, projection.voxel_norm

    @jit
    def integrate_voxel(
        tsdf_weight: Any,
        colour_volume: Any,
        index: tuple,
        offsets: tuple,
        base: Any,
        steps: Any,
        intrinsics: Any,
        image_size: tuple,
        ray_distance: Any,
        limits: tuple,
        colour: Any,
        colour_weights: Any,
        fuse_colour: bool,
    ) -> None:
        """One voxel of kintinuous_ref.tsdf.integrate (paper III, VI-A), in place: logical voxel
        `index` = (i, j, k) at p_c = base + i a_x + j a_y + k a_z (float32, the reference's
        order of additions), projected (project_voxel), its sdf, then fuse_voxel on its array
        cell (the buffer's `offsets` = (o0, o1, o2))."""
        i, j, k = index
        o0, o1, o2 = offsets
        px, py, pz = column_start(base, steps, np.float32(i), np.float32(j))
        fk = np.float32(k)
        x, y, z = px + fk * steps[2, 0], py + fk * steps[2, 1], pz + fk * steps[2, 2]
        n = tsdf_weight.shape[0]
        voxel = (cell(i, o0, n), cell(j, o1, n), cell(k, o2, n))
        pixel = project_voxel(x, y, z, intrinsics, image_size)
        sdf = ray_distance[pixel] - voxel_norm(x, y, z)
        fuse_voxel(
            tsdf_weight,
            colour_volume,
            voxel,
            pixel,
            sdf,
            limits,
            colour,
            colour_weights,
            fuse_colour,
        )

    @jit
    def limit_interval(lo: float, hi: float, a: float, b: float) -> tuple:
        """[lo, hi] intersected with {k : a + b k >= 0}."""
        if b > 0:
            return max(lo, -a / b), hi
        if b < 0:
            return lo, min(hi, -a / b)
        if a < 0:
            return 1.0, 0.0  # never: empty
        return lo, hi

    @jit
    def column_range(
        start: tuple, step: tuple, intrinsics: Any, image_size: tuple, far: float, n: int
    ) -> tuple:
        """[k0, k1) holding every k of the voxel column p_c(k) = p + k a that the frame can
        update: 0 < z <= far (the largest depth + mu bounds z, as |p_c| <= lambda D + mu) and
        the projection within half a pixel of the image (u in [-1, W], v in [-1, H], i.e.
        fx x + (cx + 1) z >= 0 and (W - cx) z - fx x >= 0 for z > 0, linear in k). A margin of
        one voxel at each end covers float32 rounding of the voxel positions; fuse_voxel's
        sdf test still makes the exact decision, so only voxels it would skip are left out.
        `start` = p and `step` = a (float64), `image_size` = (W, H)."""
        px, py, pz = start
        ax, ay, az = step
        width, height = image_size
        fx, fy = float(intrinsics[0]), float(intrinsics[1])
        cx, cy = float(intrinsics[2]), float(intrinsics[3])
        lo, hi = -1.0, float(n)
        lo, hi = limit_interval(lo, hi, pz, az)
        lo, hi = limit_interval(lo, hi, far - pz, -az)
        lo, hi = limit_interval(lo, hi, fx * px + (cx + 1.0) * pz, fx * ax + (cx + 1.0) * az)
        lo, hi = limit_interval(lo, hi, (width - cx) * pz - fx * px, (width - cx) * az - fx * ax)
        lo, hi = limit_interval(lo, hi, fy * py + (cy + 1.0) * pz, fy * ay + (cy + 1.0) * az)
        lo, hi = limit_interval(lo, hi, (height - cy) * pz - fy * py, (height - cy) * az - fy * ay)
        if not lo <= hi:
            return 0, 0
        k0 = max(int(math.floor(lo)) - 1, 0)
        k1 = min(int(math.ceil(hi)) + 2, n)
        return k0, max(k1, k0)

    return SimpleNamespace(
        column_range=column_range, integrate_voxel=integrate_voxel, limit_interval=limit_interval
    )


def build_colour_weight(jit: Callable[[Any], Any]) -> SimpleNamespace:
    """A pixel's colour weight (kintinuous_fast.colour's kernels)."""

    @jit
    def colour_weight(
        depth: Any, fusable: bool, normal_z: Any, use_mask: bool, use_angle: bool
    ) -> Any:
        """kintinuous_ref.colour.colour_weights of one pixel (paper VI-B), float32: 1 where
        there is depth, times the discontinuity mask's `fusable` when use_mask, times |n_z|
        (0 where not finite) when use_angle. The reference's factors are 0, 1 and |n_z|: their
        float32 product is |n_z| or 0 in any order, so the weights are bit-identical."""
        weight = np.float32(1.0) if depth > 0 else np.float32(0.0)
        if use_mask and not fusable:
            weight = np.float32(0.0)
        if use_angle:
            nz = abs(np.float32(normal_z))
            weight *= nz if math.isfinite(nz) else np.float32(0.0)
        return weight

    return SimpleNamespace(colour_weight=colour_weight)
