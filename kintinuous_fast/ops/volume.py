"""Per-voxel and per-ray maths of kintinuous_ref.tsdf, .raycast and .colour, written once for the
CPU and the CUDA target.

The fast volume stores what the GPU design of Kintinuous stores, 8 bytes per voxel (1 GiB at
512^3): `tsdf_weight` (N, N, N, 2) int16 holds round(F * 32767) and the integer weight W (the
reference's weights are integers too: +1 per frame, capped), and `colour` (N, N, N, 4) uint8 holds
R, G, B and the colour weight rounded to an integer (at least 1 once any colour arrived). The
reference keeps float32 for all of them; the arithmetic below is the reference's, in the same
precision and order, with a rounding to the stored type at the end of each update.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from types import SimpleNamespace
from typing import Any

import numpy as np

from kintinuous_fast.ops import build_rint

TSDF_SCALE = 32767.0  # int16 units per unit of normalised TSDF
TSDF_MAX = 32767  # the stored F = 1
TSDF_INVERSE_SCALE = 1.0 / TSDF_SCALE
BRICK = 8  # voxels per side of the empty-space bricks (kintinuous_ref.raycast.BRICK)
# Voxels per side of the fine bricks whose observed negative voxels integration counts (the cpu
# raycast's second level of empty-space skipping, inside the bricks next to a surface).
FINE = 2
# Voxels by which the cpu raycast's jumps shrink an empty cube: far above the rounding of sample
# coordinates (~1e-13 voxels), far below a sample step (~2 voxels).
JUMP_MARGIN = 1e-6
# Bricks at a distance below this take the cpu raycast's jumps from its fine distance map (in
# FINE^3 bricks, capped; valid everywhere): near surfaces they are longer than the brick
# map's, whose cube of radius D - 1 is a single brick at D = 1.
FINE_LEVEL_BELOW = 4
# The cpu raycast's tile cones (cone_safe_until): the slack, in voxels, by which the box of rays
# stays inside a safe cube (far above rounding, ~1e-13 voxels), the most cubes walked, and the
# voxels past the box's leading face where the next cube is looked up (also the least advance,
# along the ray's dominant axis, worth another cube).
CONE_MARGIN = 1e-3
CONE_STEPS = 64
CONE_LOOKAHEAD = 0.5

# Cyclical buffer (kintinuous_ref.tsdf, moving volume): logical voxel l lives in array cell
# (l + offset) mod N, offset in [0, N). Every function below takes the offset as three ints
# (o0, o1, o2) and maps logical indices with `cell` (one compare, no division).


def build_ops(
    jit: Callable[[Any], Any], jit_called: Callable[[Any], Any] | None = None
) -> SimpleNamespace:
    """The scalar functions of integration and raycasting compiled with `jit`; the few large
    per-ray ones (a whole march, a normal, a colour) with `jit_called` (default `jit`). The cpu
    backend's `jit` inlines at numba IR level, which is what makes the per-voxel loops fast, but
    inlining a whole march and its samples into every caller made the raycast take minutes to
    compile; called once per ray, these lose nothing by being calls."""
    jit_called = jit_called or jit

    @jit
    def dequantise(q: Any) -> Any:
        """float32 TSDF of a stored int16: q / 32767 correctly rounded to float32, the division
        to_reference_volume does. Computed as a float64 product (a float32 division costs ~4x a
        multiply, and the raycast's normals take 48 of them): its error (~1e-16 relative) is far
        below the gap between q / 32767 and any float32 rounding midpoint (> 2^-39 relative,
        as 32767 is odd), so it rounds the same way; checked for every int16 by the tests."""
        return np.float32(float(q) * TSDF_INVERSE_SCALE)

    @jit
    def quantise(f: Any) -> int:
        """Nearest int16 of F * 32767, F in [-1, 1]."""
        q = round(float(f) * TSDF_SCALE)
        return min(max(q, -32767), 32767)

    @jit
    def ray_distance_pixel(
        d: Any, u: int, v: int, fx: float, fy: float, cx: float, cy: float
    ) -> Any:
        """lambda D: the measured distance along pixel (u, v)'s ray (float32 as the reference);
        -inf where D is not > 0 (no measurement), so that every sdf taken from it is below -mu:
        no update, as the reference's D > 0 test."""
        x = (u - cx) * 1.0 / fx
        y = (v - cy) * 1.0 / fy
        measured = np.float32(float(d) * math.sqrt(x * x + y * y + 1.0))
        return measured if d > 0 else np.float32(-np.inf)

    @jit
    def cell(index: int, offset: int, n: int) -> int:
        """Array cell of logical index `index` in [0, N) with buffer offset in [0, N), unsigned:
        numba then indexes without its negative-index wraparound (a compare and select per
        index, which also keeps LLVM from vectorising)."""
        c = index + offset
        return np.uint64(c - n if c >= n else c)

    rint32 = build_rint(jit)[1]

    @jit
    def project_voxel(x: Any, y: Any, z: Any, intrinsics: Any, width: int, height: int) -> Any:
        """The pixel of a camera-frame voxel centre, (u, v) = round(pi(p_c)) (float32, as NumPy 2
        computes the reference's projection), as the flat index v W + u (uint32); W H, the
        "no pixel" slot one past the image, when z <= 0 or it falls outside the image. Images
        are read flat here: ray distances (ray_distance_pixel's, H W + 1 with -inf in that
        slot), colour (H W, 3), colour weights (H W). Selects only, no branch and no
        integer-to-float conversion, so that a loop of it vectorises (the cpu integration's
        first pass)."""
        uf = intrinsics[0] * x / z + intrinsics[2]
        vf = intrinsics[1] * y / z + intrinsics[3]
        ur = rint32(uf)  # float32: a float64 rounding costs 10 % of integration (measured)
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
    def update_voxel(
        tsdf_weight: Any,
        colour_volume: Any,
        ci: int,
        cj: int,
        ck: int,
        x: Any,
        y: Any,
        z: Any,
        intrinsics: Any,
        width: int,
        height: int,
        ray_distance: Any,
        truncation: Any,
        max_weight: Any,
        colour: Any,
        colour_weights: Any,
        fuse_colour: bool,
        colour_max_weight: Any,
    ) -> int:
        """One voxel of kintinuous_ref.tsdf.integrate (paper III, VI-A), in place: the voxel in
        array cell (ci, cj, ck) whose camera-frame centre is (x, y, z) (float32):
        project_voxel, its sdf, then fuse_voxel. Returns fuse_voxel's change of the negative
        count."""
        pixel = project_voxel(x, y, z, intrinsics, width, height)
        return fuse_voxel(
            tsdf_weight, colour_volume, ci, cj, ck, pixel,
            ray_distance[pixel] - voxel_norm(x, y, z), truncation, max_weight,
            colour, colour_weights, fuse_colour, colour_max_weight,
        )  # fmt: skip

    @jit
    def fuse_voxel(
        tsdf_weight: Any,
        colour_volume: Any,
        ci: int,
        cj: int,
        ck: int,
        pixel: Any,
        sdf: Any,
        truncation: Any,
        max_weight: Any,
        colour: Any,
        colour_weights: Any,
        fuse_colour: bool,
        colour_max_weight: Any,
    ) -> int:
        """The update of the voxel in array cell (ci, cj, ck) projecting to flat pixel index
        `pixel` (project_voxel's), with sdf = lambda D - |p_c| (-inf without a measurement).

        Update if sdf >= -mu: running average of min(1, sdf/mu) with weight W + 1 (capped);
        colour where |sdf| < mu and the pixel's colour weight > 0.

        Returns how the voxel's "observed and negative" state changed (+1, 0 or -1): the cpu
        backend keeps a count of such voxels per fine brick for the raycast's empty-space
        skipping. Values that do not change are not written back (a saturated free-space voxel,
        F = 1 at the weight cap, stays as it is: no store, no dirty cache line).
        """
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

    @jit
    def column_start(base: Any, steps: Any, fi: Any, fj: Any) -> tuple:
        """Camera-frame centre of voxel (i, j, 0): base + i a_x + j a_y in float32, the
        reference's order of additions (a column then adds k a_z)."""
        return (
            (base[0] + fi * steps[0, 0]) + fj * steps[1, 0],
            (base[1] + fi * steps[0, 1]) + fj * steps[1, 1],
            (base[2] + fi * steps[0, 2]) + fj * steps[1, 2],
        )

    @jit
    def integrate_voxel(
        tsdf_weight: Any,
        colour_volume: Any,
        i: int,
        j: int,
        k: int,
        o0: int,
        o1: int,
        o2: int,
        base: Any,
        steps: Any,
        intrinsics: Any,
        width: int,
        height: int,
        ray_distance: Any,
        truncation: Any,
        max_weight: Any,
        colour: Any,
        colour_weights: Any,
        fuse_colour: bool,
        colour_max_weight: Any,
    ) -> None:
        """Logical voxel (i, j, k): p_c = base + i a_x + j a_y + k a_z (float32, the
        reference's order of additions), then update_voxel on its array cell."""
        px, py, pz = column_start(base, steps, np.float32(i), np.float32(j))
        fk = np.float32(k)
        x = px + fk * steps[2, 0]
        y = py + fk * steps[2, 1]
        z = pz + fk * steps[2, 2]
        n = tsdf_weight.shape[0]
        update_voxel(
            tsdf_weight,
            colour_volume,
            cell(i, o0, n),
            cell(j, o1, n),
            cell(k, o2, n),
            x,
            y,
            z,
            intrinsics,
            width,
            height,
            ray_distance,
            truncation,
            max_weight,
            colour,
            colour_weights,
            fuse_colour,
            colour_max_weight,
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
        px: float,
        py: float,
        pz: float,
        ax: float,
        ay: float,
        az: float,
        intrinsics: Any,
        width: int,
        height: int,
        far: float,
        n: int,
    ) -> tuple:
        """[k0, k1) holding every k of the voxel column p_c(k) = p + k a that update_voxel can
        change: 0 < z <= far (the largest depth + mu bounds z, as |p_c| <= lambda D + mu) and
        the projection within half a pixel of the image (u in [-1, W], v in [-1, H], i.e.
        fx x + (cx + 1) z >= 0 and (W - cx) z - fx x >= 0 for z > 0, linear in k). A margin of
        one voxel at each end covers float32 rounding of the voxel positions; update_voxel
        still makes the exact decision, so only voxels it would skip are left out."""
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

    @jit
    def sample_tsdf_at(
        tsdf_weight: Any, o0: int, o1: int, o2: int, cx: float, cy: float, cz: float
    ) -> float:
        """Trilinear TSDF over the OBSERVED corners only (weights renormalised), float64;
        NaN outside [0, N-1]^3 or when no corner is observed (kintinuous_ref.tsdf.sample_tsdf).
        (cx, cy, cz) are logical voxel coordinates."""
        n = tsdf_weight.shape[0]
        if not (cx >= 0 and cx <= n - 1 and cy >= 0 and cy <= n - 1 and cz >= 0 and cz <= n - 1):
            return np.nan
        bx = min(max(int(math.floor(cx)), 0), n - 2)
        by = min(max(int(math.floor(cy)), 0), n - 2)
        bz = min(max(int(math.floor(cz)), 0), n - 2)
        fx = min(max(cx - bx, 0.0), 1.0)
        fy = min(max(cy - by, 0.0), 1.0)
        fz = min(max(cz - bz, 0.0), 1.0)
        total = 0.0
        coverage = 0.0
        for a in range(2):
            wa = fx if a else 1.0 - fx
            ia = cell(bx + a, o0, n)
            for b in range(2):
                wb = fy if b else 1.0 - fy
                ib = cell(by + b, o1, n)
                for c in range(2):
                    wc = fz if c else 1.0 - fz
                    ic = cell(bz + c, o2, n)
                    if tsdf_weight[ia, ib, ic, 1] > 0:
                        w = wa * wb * wc
                        total += w * float(dequantise(tsdf_weight[ia, ib, ic, 0]))
                        coverage += w
        if not coverage > 1e-6:
            return np.nan
        return total / coverage

    @jit
    def trilinear_tsdf(
        tsdf_weight: Any, o0: int, o1: int, o2: int, cx: float, cy: float, cz: float
    ) -> Any:
        """Plain trilinear TSDF (unobserved voxels count as 0), float32 like tsdf.trilinear."""
        n = tsdf_weight.shape[0]
        bx = min(max(int(math.floor(cx)), 0), n - 2)
        by = min(max(int(math.floor(cy)), 0), n - 2)
        bz = min(max(int(math.floor(cz)), 0), n - 2)
        fx = min(max(cx - bx, 0.0), 1.0)
        fy = min(max(cy - by, 0.0), 1.0)
        fz = min(max(cz - bz, 0.0), 1.0)
        total = 0.0
        for a in range(2):
            wa = fx if a else 1.0 - fx
            ia = cell(bx + a, o0, n)
            for b in range(2):
                wb = fy if b else 1.0 - fy
                ib = cell(by + b, o1, n)
                for c in range(2):
                    wc = fz if c else 1.0 - fz
                    value = float(dequantise(tsdf_weight[ia, ib, cell(bz + c, o2, n), 0]))
                    total += wa * wb * wc * value
        return np.float32(total)

    @jit
    def clip(c: float, limit: float) -> float:
        return min(max(c, 0.0), limit)

    @jit_called
    def gradient_normal(
        tsdf_weight: Any, o0: int, o1: int, o2: int, cx: float, cy: float, cz: float
    ) -> tuple:
        """Unit TSDF gradient by central differences one voxel apart (raycast._gradient_normals);
        NaN when it vanishes."""
        limit = tsdf_weight.shape[0] - 1.0
        px, py, pz = clip(cx, limit), clip(cy, limit), clip(cz, limit)
        t = tsdf_weight
        gx = trilinear_tsdf(t, o0, o1, o2, clip(cx + 1.0, limit), py, pz) - trilinear_tsdf(
            t, o0, o1, o2, clip(cx - 1.0, limit), py, pz
        )
        gy = trilinear_tsdf(t, o0, o1, o2, px, clip(cy + 1.0, limit), pz) - trilinear_tsdf(
            t, o0, o1, o2, px, clip(cy - 1.0, limit), pz
        )
        gz = trilinear_tsdf(t, o0, o1, o2, px, py, clip(cz + 1.0, limit)) - trilinear_tsdf(
            t, o0, o1, o2, px, py, clip(cz - 1.0, limit)
        )
        gx, gy, gz = float(gx), float(gy), float(gz)
        length = math.sqrt(gx * gx + gy * gy + gz * gz)
        if not length > 0:
            return np.nan, np.nan, np.nan
        return gx / length, gy / length, gz / length

    @jit_called
    def surface_colour_at(
        colour_volume: Any, o0: int, o1: int, o2: int, cx: float, cy: float, cz: float
    ) -> tuple:
        """RGB at continuous voxel coordinates by trilinear interpolation over the voxels that
        received colour (colour.surface_colour); black where none or outside the grid."""
        n = colour_volume.shape[0]
        if not (cx >= 0 and cx <= n - 1 and cy >= 0 and cy <= n - 1 and cz >= 0 and cz <= n - 1):
            return 0, 0, 0
        bx = min(max(int(math.floor(cx)), 0), n - 2)
        by = min(max(int(math.floor(cy)), 0), n - 2)
        bz = min(max(int(math.floor(cz)), 0), n - 2)
        fx, fy, fz = cx - bx, cy - by, cz - bz
        r = 0.0
        g = 0.0
        b_ = 0.0
        coverage = 0.0
        for a in range(2):
            wa = fx if a else 1.0 - fx
            ia = cell(bx + a, o0, n)
            for b in range(2):
                wb = fy if b else 1.0 - fy
                ib = cell(by + b, o1, n)
                for c in range(2):
                    wc = fz if c else 1.0 - fz
                    ic = cell(bz + c, o2, n)
                    if colour_volume[ia, ib, ic, 3] > 0:
                        w = wa * wb * wc
                        r += w * float(colour_volume[ia, ib, ic, 0])
                        g += w * float(colour_volume[ia, ib, ic, 1])
                        b_ += w * float(colour_volume[ia, ib, ic, 2])
                        coverage += w
        if not coverage > 1e-6:
            return 0, 0, 0
        return (
            min(max(round(r / coverage), 0), 255),
            min(max(round(g / coverage), 0), 255),
            min(max(round(b_ / coverage), 0), 255),
        )

    @jit
    def axis_interval(o: float, d: float, lower: float, upper: float) -> tuple:
        """(t_min, t_max) of one slab [lower, upper] along one axis (infinite when parallel)."""
        if d == 0:
            if o >= lower and o <= upper:
                return -np.inf, np.inf
            return np.inf, -np.inf
        t0 = (lower - o) / d
        t1 = (upper - o) / d
        return min(t0, t1), max(t0, t1)

    @jit
    def ray_span(
        origin: Any, d0: float, d1: float, d2: float, volume_origin: Any, voxel_size: float, n: int
    ) -> tuple:
        """(entry, exit): the ray parameters where the ray is inside the volume's sample box
        [0, N - 1]^3 (entry >= 0; empty when entry >= exit)."""
        upper_offset = (n - 1) * voxel_size
        lo0, hi0 = axis_interval(origin[0], d0, volume_origin[0], volume_origin[0] + upper_offset)
        lo1, hi1 = axis_interval(origin[1], d1, volume_origin[1], volume_origin[1] + upper_offset)
        lo2, hi2 = axis_interval(origin[2], d2, volume_origin[2], volume_origin[2] + upper_offset)
        return max(max(max(lo0, lo1), lo2), 0.0), min(min(hi0, hi1), hi2)

    @jit
    def zero_crossing(t0: float, f0: float, t1: float, f1: float) -> float:
        return t0 + (t1 - t0) * f0 / (f0 - f1)

    @jit
    def sample_along(
        tsdf_weight: Any,
        o0: int,
        o1: int,
        o2: int,
        origin: Any,
        d0: float,
        d1: float,
        d2: float,
        t: float,
        volume_origin: Any,
        voxel_size: float,
    ) -> float:
        cx = (origin[0] + t * d0 - volume_origin[0]) / voxel_size
        cy = (origin[1] + t * d1 - volume_origin[1]) / voxel_size
        cz = (origin[2] + t * d2 - volume_origin[2]) / voxel_size
        return sample_tsdf_at(tsdf_weight, o0, o1, o2, cx, cy, cz)

    @jit
    def refine_crossing(
        tsdf_weight: Any,
        o0: int,
        o1: int,
        o2: int,
        origin: Any,
        d0: float,
        d1: float,
        d2: float,
        t0: float,
        f0: float,
        t1: float,
        f1: float,
        volume_origin: Any,
        voxel_size: float,
    ) -> float:
        """The ray distance of the surface between samples t0 (F > 0) and t1 (F < 0): one
        secant step, then a second on whichever side the estimate falls (the reference's)."""
        estimate = zero_crossing(t0, f0, t1, f1)
        f = sample_along(
            tsdf_weight, o0, o1, o2, origin, d0, d1, d2, estimate, volume_origin, voxel_size
        )
        if f > 0:
            return zero_crossing(estimate, f, t1, f1)
        if f < 0:
            return zero_crossing(t0, f0, estimate, f)
        return estimate

    @jit
    def fine_index(c: float, n: int, last: int) -> int:
        """Fine brick of the lower corner voxel of a sample at voxel coordinate c (clamped as
        sample_tsdf_at clamps it), at most `last`."""
        return min(min(max(int(math.floor(c)), 0), n - 2) // FINE, last)

    @jit
    def samples_to_leave(c: float, dc: float, inverse: float, lower: float, upper: float) -> float:
        """Samples (a real number) until the coordinate c + m dc leaves [lower, upper) shrunk
        by JUMP_MARGIN voxels, `inverse` = 1 / dc; inf when dc = 0. The margin dwarfs the
        rounding of the samples' exactly computed coordinates (~1e-13 voxels), so every sample
        before the returned count lies inside [lower, upper) as computed."""
        if dc > 0:
            return (upper - JUMP_MARGIN - c) * inverse
        if dc < 0:
            return (lower + JUMP_MARGIN - c) * inverse
        return np.inf

    @jit
    def first_sample_outside(
        m: int,
        cx: float,
        cy: float,
        cz: float,
        dcx: float,
        dcy: float,
        dcz: float,
        ix: float,
        iy: float,
        iz: float,
        lower_x: float,
        lower_y: float,
        lower_z: float,
        size: float,
    ) -> int:
        """Index of the first sample after sample m (at voxel coordinates c, advancing dc per
        sample, i = 1 / dc) that may lie outside the cube [lower, lower + size)^3; at least
        m + 1. Multiplications only: the margin of samples_to_leave keeps it conservative."""
        to_leave = min(
            min(
                samples_to_leave(cx, dcx, ix, lower_x, lower_x + size),
                samples_to_leave(cy, dcy, iy, lower_y, lower_y + size),
            ),
            samples_to_leave(cz, dcz, iz, lower_z, lower_z + size),
        )
        return m + max(int(math.floor(to_leave)) + 1, 1)

    @jit
    def inverse_or_zero(x: float) -> float:
        return 1.0 / x if x != 0 else 0.0

    @jit_called
    def march_ray(
        tsdf_weight: Any,
        o0: int,
        o1: int,
        o2: int,
        empty: Any,
        fine_distance: Any,
        origin: Any,
        d0: float,
        d1: float,
        d2: float,
        volume_origin: Any,
        voxel_size: float,
        step: float,
        safe_until: float,
    ) -> float:
        """Ray parameter of the first + to - crossing (regula-falsi refined), NaN if none; the
        samples lie at entry + m step (kintinuous_ref.raycast.march), marched from the first
        sample at or past `safe_until` (cone_safe_until's: no sample before it can be negative,
        so they are skipped like those of a jump; 0 starts at the entry).

        Empty space is skipped exactly with a distance map at two levels. `empty` is the brick
        distance map of kintinuous_ref.raycast._empty_space (logical bricks of BRICK^3 voxels):
        no sample in the cube of bricks within D - 1 of a brick at distance D can be negative,
        as there. `fine_distance` is finer, over FINE^3 bricks: fine_distance[f] = D >= 1 says
        no fine brick within chessboard distance D - 1 of f is `near` (may hold the lower
        corner of a negative sample), so every sample whose lower corner lies in that cube is
        >= 0 or unknown and, unless the sample before the first of them was negative, is
        skipped at once. Bricks at a distance below FINE_LEVEL_BELOW read the fine map. Maps
        of shape (1, 1, 1) holding 0 skip nothing: the plain march. Jump lengths come from
        the samples' nominal coordinates (linear in the sample index) with a margin, so the
        samples skipped are a subset of those the exact test would skip: the same answer.
        The march is march_start, then march_step until it says the ray is done.
        """
        ray = march_start(
            origin, d0, d1, d2, volume_origin, voxel_size, tsdf_weight.shape[0], step, safe_until
        )
        m, previous, previous_known, hit = ray[0], np.nan, ray[0] == 0, np.nan
        while m >= 0:
            m, previous, previous_known, hit = march_step(
                tsdf_weight, o0, o1, o2, empty, fine_distance, origin, d0, d1, d2,
                volume_origin, voxel_size, step, ray, m, previous, previous_known,
            )  # fmt: skip
        return hit

    @jit_called
    def march_two_rays(
        tsdf_weight: Any,
        o0: int,
        o1: int,
        o2: int,
        empty: Any,
        fine_distance: Any,
        origin: Any,
        a: tuple,
        b: tuple,
        volume_origin: Any,
        voxel_size: float,
        step: float,
        safe_until: float,
    ) -> tuple:
        """march_ray of two rays (unit directions a and b) in lockstep: each step of
        one is a chain of dependent loads and roundings, so the core works on the other's
        meanwhile. The same answers as marching them one after the other."""
        n = tsdf_weight.shape[0]
        ray_a = march_start(
            origin, a[0], a[1], a[2], volume_origin, voxel_size, n, step, safe_until
        )
        ray_b = march_start(
            origin, b[0], b[1], b[2], volume_origin, voxel_size, n, step, safe_until
        )
        m_a, previous_a, known_a, hit_a = ray_a[0], np.nan, ray_a[0] == 0, np.nan
        m_b, previous_b, known_b, hit_b = ray_b[0], np.nan, ray_b[0] == 0, np.nan
        while m_a >= 0 or m_b >= 0:
            if m_a >= 0:
                m_a, previous_a, known_a, hit_a = march_step(
                    tsdf_weight, o0, o1, o2, empty, fine_distance, origin, a[0], a[1], a[2],
                    volume_origin, voxel_size, step, ray_a, m_a, previous_a, known_a,
                )  # fmt: skip
            if m_b >= 0:
                m_b, previous_b, known_b, hit_b = march_step(
                    tsdf_weight, o0, o1, o2, empty, fine_distance, origin, b[0], b[1], b[2],
                    volume_origin, voxel_size, step, ray_b, m_b, previous_b, known_b,
                )  # fmt: skip
        return hit_a, hit_b

    @jit
    def march_start(
        origin: Any,
        d0: float,
        d1: float,
        d2: float,
        volume_origin: Any,
        voxel_size: float,
        n: int,
        step: float,
        safe_until: float,
    ) -> tuple:
        """(m, entry, exit, sx, sy, sz, dcx, dcy, dcz, ix, iy, iz) of a skipping march: the first
        sample m to look at (-1: the ray has none), the ray's span in the volume, the voxel
        coordinates of sample 0, their advance per sample and its inverses (0 where none)."""
        entry, exit_ = ray_span(origin, d0, d1, d2, volume_origin, voxel_size, n)
        m = 0
        if not entry < exit_:
            m = -1
        elif safe_until > entry:
            if not safe_until <= exit_:
                m = -1
            else:
                m = int(math.ceil((safe_until - entry) / step))
                if not entry + m * step <= exit_:
                    m = -1
        # voxel coordinates of sample m, nominally: start + m * per_sample (jump lengths only)
        dcx, dcy, dcz = step * d0 / voxel_size, step * d1 / voxel_size, step * d2 / voxel_size
        return (
            m,
            entry,
            exit_,
            (origin[0] + entry * d0 - volume_origin[0]) / voxel_size,
            (origin[1] + entry * d1 - volume_origin[1]) / voxel_size,
            (origin[2] + entry * d2 - volume_origin[2]) / voxel_size,
            dcx,
            dcy,
            dcz,
            inverse_or_zero(dcx),
            inverse_or_zero(dcy),
            inverse_or_zero(dcz),
        )

    @jit
    def march_step(
        tsdf_weight: Any,
        o0: int,
        o1: int,
        o2: int,
        empty: Any,
        fine_distance: Any,
        origin: Any,
        d0: float,
        d1: float,
        d2: float,
        volume_origin: Any,
        voxel_size: float,
        step: float,
        ray: tuple,
        m: int,
        previous: float,
        previous_known: bool,
    ) -> tuple:
        """One step of march_ray at sample m: a jump or a sample. Returns (m,
        previous, previous_known, hit) for the next step; m = -1 once the ray is done, hit then
        its answer (NaN: no surface)."""
        entry, exit_ = ray[1], ray[2]
        t = entry + m * step
        # The maps are read at the nominal coordinates (one multiply-add, no division). They
        # differ from the exact ones (the reference's, used for the samples) by rounding
        # only, so they name the same brick and fine brick unless within JUMP_MARGIN of a
        # fine brick's face: there the exact ones decide.
        cx, cy, cz = ray[3] + m * ray[6], ray[4] + m * ray[7], ray[5] + m * ray[8]
        if not (clear_of_faces(cx) and clear_of_faces(cy) and clear_of_faces(cz)):
            cx, cy, cz = voxel_coordinates(origin, d0, d1, d2, t, volume_origin, voxel_size)
        bricks = empty.shape[0]
        bx = min(max(int(math.floor(cx / BRICK)), 0), bricks - 1)
        by = min(max(int(math.floor(cy / BRICK)), 0), bricks - 1)
        bz = min(max(int(math.floor(cz / BRICK)), 0), bricks - 1)
        radius = int(empty[bx, by, bz])
        fine, fx, fy, fz = 0, 0, 0, 0
        if radius < FINE_LEVEL_BELOW and not (previous_known and previous < 0):
            n, last_fine = tsdf_weight.shape[0], fine_distance.shape[0] - 1
            fx = fine_index(cx, n, last_fine)
            fy = fine_index(cy, n, last_fine)
            fz = fine_index(cz, n, last_fine)
            fine = int(fine_distance[fx, fy, fz])
        if radius >= FINE_LEVEL_BELOW:  # far from surfaces: past the empty cube of bricks
            reach = radius - 1
            m_next = first_sample_outside(
                m, cx, cy, cz, ray[6], ray[7], ray[8], ray[9], ray[10], ray[11],
                (bx - reach) * BRICK, (by - reach) * BRICK, (bz - reach) * BRICK,
                (2 * reach + 1) * BRICK,
            )  # fmt: skip
            previous_known = False
        elif fine > 0:  # no sample in the cube of fine bricks can be negative: jump past it
            reach = fine - 1
            m_next = first_sample_outside(
                m, cx, cy, cz, ray[6], ray[7], ray[8], ray[9], ray[10], ray[11],
                (fx - reach) * FINE, (fy - reach) * FINE, (fz - reach) * FINE,
                (2 * reach + 1) * FINE,
            )  # fmt: skip
            previous_known = False
        else:
            value = sample_along(
                tsdf_weight, o0, o1, o2, origin, d0, d1, d2, t, volume_origin, voxel_size
            )
            # A skipped sample is >= 0 or unknown, so after a jump the one before matters
            # only if this one is negative (a crossing, never a back face): fetched then.
            if not previous_known and value < 0:
                previous = np.nan
                if m > 0:
                    previous = sample_along(
                        tsdf_weight, o0, o1, o2, origin, d0, d1, d2,
                        entry + (m - 1) * step, volume_origin, voxel_size,
                    )  # fmt: skip
            elif not previous_known:
                previous = np.nan
            if previous > 0 and value < 0:
                hit = refine_crossing(
                    tsdf_weight, o0, o1, o2, origin, d0, d1, d2, t - step, previous, t,
                    value, volume_origin, voxel_size,
                )  # fmt: skip
                return -1, previous, True, hit
            if previous < 0 and value > 0:
                return -1, previous, True, np.nan  # a back face
            previous = value
            previous_known = True
            m_next = m + 1
        if not entry + m_next * step <= exit_:
            return -1, previous, previous_known, np.nan
        return m_next, previous, previous_known, np.nan

    @jit
    def box_inside(c: float, half: float, lower: float, upper: float) -> bool:
        """Whether [c - half, c + half] lies in [lower, upper] with CONE_MARGIN to spare."""
        return c - half >= lower + CONE_MARGIN and c + half <= upper - CONE_MARGIN

    @jit
    def box_advance(
        c: float, half: float, v: float, spread: float, lower: float, upper: float
    ) -> float:
        """Largest dt keeping [c - half, c + half] inside [lower, upper] (less CONE_MARGIN)
        while its centre moves at v and its half-width grows at `spread` per unit of dt."""
        dt = np.inf
        if v + spread > 0:
            dt = (upper - CONE_MARGIN - c - half) / (v + spread)
        if v - spread < 0:
            dt = min(dt, (c - half - lower - CONE_MARGIN) / (spread - v))
        return dt

    @jit_called
    def cone_safe_until(
        empty: Any,
        fine_distance: Any,
        n: int,
        origin: Any,
        d0: float,
        d1: float,
        d2: float,
        spread: float,
        volume_origin: Any,
        voxel_size: float,
        start: float,
    ) -> float:
        """A ray parameter T >= `start` (where none of the rays has entered the volume yet)
        such that no sample at t <= T of any ray whose unit direction
        differs from (d0, d1, d2) by at most `spread` in each component can be negative: the
        shared free space in front of a tile of pixels, marched once for all its rays.

        At t those rays lie in a box of half-width t * spread / voxel_size voxels around the
        centre ray's point. The box is walked through the safe cubes of the two distance maps
        (march_ray's: samples whose brick, or whose lower corner's fine brick, lies in
        the cube cannot be negative), each time as far as it stays inside the cube, choosing
        the cube just ahead of the centre; the walk stops where no cube holds the whole box
        (next to the tile's nearest surface). Points outside [0, N - 1]^3 are no samples: the
        box may start and end outside the volume."""
        sx = (origin[0] - volume_origin[0]) / voxel_size
        sy = (origin[1] - volume_origin[1]) / voxel_size
        sz = (origin[2] - volume_origin[2]) / voxel_size
        vx, vy, vz = d0 / voxel_size, d1 / voxel_size, d2 / voxel_size
        grow = spread / voxel_size
        # The next cube is the one around a point just past the box's leading face along the
        # ray's dominant axis (the face the last advance stopped at, unless growth stopped it).
        dominant = max(max(abs(vx), abs(vy)), abs(vz))
        # Lower corners are clamped to N - 2: past it, that names another fine brick than the
        # coordinates do only when N - 1 starts a fine brick.
        top = n - 2.0 if (n - 1) % FINE == 0 else np.inf
        t = start
        for _ in range(CONE_STEPS):
            cx, cy, cz = sx + t * vx, sy + t * vy, sz + t * vz
            half = t * grow
            if not (
                box_inside(cx, half, -np.inf, top)
                and box_inside(cy, half, -np.inf, top)
                and box_inside(cz, half, -np.inf, top)
            ):
                return t
            ahead = (half + CONE_LOOKAHEAD) / dominant
            ax = min(max(cx + ahead * vx, 0.0), n - 1.0)
            ay = min(max(cy + ahead * vy, 0.0), n - 1.0)
            az = min(max(cz + ahead * vz, 0.0), n - 1.0)
            # clamped as march_step clamps them (a (1, 1, 1) map of 0 then skips nothing)
            last_brick, last_fine = empty.shape[0] - 1, fine_distance.shape[0] - 1
            bx = min(int(ax) // BRICK, last_brick)
            by = min(int(ay) // BRICK, last_brick)
            bz = min(int(az) // BRICK, last_brick)
            radius = int(empty[bx, by, bz])
            size, fx, fy, fz = BRICK, bx, by, bz
            if radius < 1 or not (
                box_inside(cx, half, (bx - radius + 1) * BRICK, (bx + radius) * BRICK)
                and box_inside(cy, half, (by - radius + 1) * BRICK, (by + radius) * BRICK)
                and box_inside(cz, half, (bz - radius + 1) * BRICK, (bz + radius) * BRICK)
            ):
                size = FINE
                fx = min(int(ax) // FINE, last_fine)
                fy = min(int(ay) // FINE, last_fine)
                fz = min(int(az) // FINE, last_fine)
                radius = int(fine_distance[fx, fy, fz])
                if radius < 1 or not (
                    box_inside(cx, half, (fx - radius + 1) * FINE, (fx + radius) * FINE)
                    and box_inside(cy, half, (fy - radius + 1) * FINE, (fy + radius) * FINE)
                    and box_inside(cz, half, (fz - radius + 1) * FINE, (fz + radius) * FINE)
                ):
                    return t
            dt = min(
                min(
                    box_advance(cx, half, vx, grow, (fx - radius + 1) * size, (fx + radius) * size),
                    box_advance(cy, half, vy, grow, (fy - radius + 1) * size, (fy + radius) * size),
                ),
                box_advance(cz, half, vz, grow, (fz - radius + 1) * size, (fz + radius) * size),
            )
            if not dt * dominant >= CONE_LOOKAHEAD:
                return t  # the box has (nearly) outgrown the cubes: leave the rest to each ray
            t += dt
        return t

    @jit
    def clear_of_faces(c: float) -> bool:
        """Whether coordinate c is more than JUMP_MARGIN voxels from every fine brick face."""
        r = c * (1.0 / FINE)
        f = r - math.floor(r)
        return f >= JUMP_MARGIN / FINE and f <= 1.0 - JUMP_MARGIN / FINE

    @jit
    def voxel_coordinates(
        origin: Any,
        d0: float,
        d1: float,
        d2: float,
        t: float,
        volume_origin: Any,
        voxel_size: float,
    ) -> tuple:
        """Continuous voxel coordinates of the ray point at t (sample_along's)."""
        cx = (origin[0] + t * d0 - volume_origin[0]) / voxel_size
        cy = (origin[1] + t * d1 - volume_origin[1]) / voxel_size
        cz = (origin[2] + t * d2 - volume_origin[2]) / voxel_size
        return cx, cy, cz

    @jit
    def ray_direction(u: int, v: int, camera: Any, rotation: Any) -> tuple:
        """Unit world-frame direction of pixel (u, v)'s ray (`camera` float64 fx, fy, cx, cy)."""
        rx = (u - camera[2]) * 1.0 / camera[0]
        ry = (v - camera[3]) * 1.0 / camera[1]
        d0 = rotation[0, 0] * rx + rotation[0, 1] * ry + rotation[0, 2]
        d1 = rotation[1, 0] * rx + rotation[1, 1] * ry + rotation[1, 2]
        d2 = rotation[2, 0] * rx + rotation[2, 1] * ry + rotation[2, 2]
        norm = math.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
        return d0 / norm, d1 / norm, d2 / norm

    @jit
    def raycast_pixels(
        tsdf_weight: Any,
        colour_volume: Any,
        has_colour: bool,
        o0: int,
        o1: int,
        o2: int,
        empty: Any,
        fine_distance: Any,
        u: int,
        v: int,
        camera: Any,
        rotation: Any,
        origin: Any,
        volume_origin: Any,
        voxel_size: float,
        step: float,
        vertices: Any,
        normals: Any,
        colours: Any,
        safe_until: float,
        partner: int,
    ) -> None:
        """Vertex, normal and colour of pixel (u, v) (kintinuous_ref.raycast.raycast) by
        march_ray from `safe_until` on (cone_safe_until of the pixel's tile, or 0), and with
        `partner` > 0 of pixel (u + partner, v) too, the two rays marched in lockstep
        (march_two_rays). `camera` is float64 (fx, fy, cx, cy); outputs were filled with NaN / 0
        beforehand."""
        a = ray_direction(u, v, camera, rotation)
        if partner > 0:
            b = ray_direction(u + partner, v, camera, rotation)
            t_a, t_b = march_two_rays(
                tsdf_weight, o0, o1, o2, empty, fine_distance, origin, a, b, volume_origin,
                voxel_size, step, safe_until,
            )  # fmt: skip
            shade_pixel(
                tsdf_weight, colour_volume, has_colour, o0, o1, o2, u + partner, v, t_b, origin,
                b[0], b[1], b[2], volume_origin, voxel_size, vertices, normals, colours,
            )  # fmt: skip
        else:
            t_a = march_ray(
                tsdf_weight, o0, o1, o2, empty, fine_distance, origin, a[0], a[1], a[2],
                volume_origin, voxel_size, step, safe_until,
            )  # fmt: skip
        shade_pixel(
            tsdf_weight, colour_volume, has_colour, o0, o1, o2, u, v, t_a, origin, a[0], a[1],
            a[2], volume_origin, voxel_size, vertices, normals, colours,
        )  # fmt: skip

    @jit
    def shade_pixel(
        tsdf_weight: Any,
        colour_volume: Any,
        has_colour: bool,
        o0: int,
        o1: int,
        o2: int,
        u: int,
        v: int,
        t: float,
        origin: Any,
        d0: float,
        d1: float,
        d2: float,
        volume_origin: Any,
        voxel_size: float,
        vertices: Any,
        normals: Any,
        colours: Any,
    ) -> None:
        """Vertex, normal and colour of pixel (u, v) whose ray met the surface at t (NaN: none)."""
        if not math.isfinite(t):
            return
        px, py, pz = origin[0] + t * d0, origin[1] + t * d1, origin[2] + t * d2
        cx = (px - volume_origin[0]) / voxel_size
        cy = (py - volume_origin[1]) / voxel_size
        cz = (pz - volume_origin[2]) / voxel_size
        nx, ny, nz = gradient_normal(tsdf_weight, o0, o1, o2, cx, cy, cz)
        if math.isnan(nx):
            return  # no usable normal: no use to ICP, dropped
        vertices[v, u, 0], vertices[v, u, 1], vertices[v, u, 2] = px, py, pz
        normals[v, u, 0], normals[v, u, 1], normals[v, u, 2] = nx, ny, nz
        if has_colour:
            r, g, b = surface_colour_at(colour_volume, o0, o1, o2, cx, cy, cz)
            colours[v, u, 0], colours[v, u, 1], colours[v, u, 2] = r, g, b

    @jit
    def count_negative(
        tsdf_weight: Any, o0: int, o1: int, o2: int, b0: int, b1: int, b2: int, size: int
    ) -> int:
        """Observed voxels with negative TSDF in the logical block (b0, b1, b2) of size^3 voxels
        (the fine bricks of the cpu raycast, the bricks of the cuda one)."""
        n = tsdf_weight.shape[0]
        count = 0
        for i in range(b0 * size, min((b0 + 1) * size, n)):
            ci = cell(i, o0, n)
            for j in range(b1 * size, min((b1 + 1) * size, n)):
                cj = cell(j, o1, n)
                for k in range(b2 * size, min((b2 + 1) * size, n)):
                    ck = cell(k, o2, n)
                    if tsdf_weight[ci, cj, ck, 0] < 0 and tsdf_weight[ci, cj, ck, 1] > 0:
                        count += 1
        return count

    return SimpleNamespace(
        cell=cell,
        column_start=column_start,
        colour_weight=colour_weight,
        count_negative=count_negative,
        cone_safe_until=cone_safe_until,
        update_voxel=update_voxel,
        project_voxel=project_voxel,
        voxel_norm=voxel_norm,
        fuse_voxel=fuse_voxel,
        column_range=column_range,
        dequantise=dequantise,
        rint32=rint32,
        ray_span=ray_span,
        quantise=quantise,
        ray_distance_pixel=ray_distance_pixel,
        integrate_voxel=integrate_voxel,
        sample_tsdf_at=sample_tsdf_at,
        trilinear_tsdf=trilinear_tsdf,
        gradient_normal=gradient_normal,
        surface_colour_at=surface_colour_at,
        march_ray=march_ray,
        march_two_rays=march_two_rays,
        ray_direction=ray_direction,
        raycast_pixels=raycast_pixels,
    )
