"""Per-ray maths of kintinuous_ref.raycast, written once for the CPU and the CUDA target: the
march along a ray with exact empty-space skipping (brick and fine distance maps),
the regula-falsi refinement of the crossing, and the shading of the hit (vertex, TSDF-gradient
normal, colour) from the voxel functions of kintinuous_fast.tsdf.voxel.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from types import SimpleNamespace
from typing import Any

import numpy as np

from kintinuous_fast.tsdf import voxel as voxel_ops
from kintinuous_fast.tsdf.voxel import BRICK, FINE

# Voxels by which the cpu raycast's jumps shrink an empty cube: far above the rounding of sample
# coordinates (~1e-13 voxels), far below a sample step (~2 voxels).
JUMP_MARGIN = 1e-6
# The cpu raycast's fine distance map (in FINE^3 bricks) is capped here: a jump then leaves a
# cube reaching at most 3 fine bricks (6 voxels) to either side. Rays start where they enter
# the first fine brick that may hold a negative sample (cpu.raycast.near_starts), so long fine
# jumps are rare: on redkitchen 1.70 jumps a ray after the start with a cap of 16, 1.72 at 8,
# 1.84 at 4, while each step of the cap costs the map two more passes (from 16 to 4 the maps
# are ~2 ms a frame cheaper and the march ~1.3 ms dearer, single thread). A step reads the
# fine map first (near surfaces its jumps are longer than the brick map's, whose cube of
# radius D - 1 is a single brick at D = 1) and the brick map only where the fine distance is
# capped, or where there is no fine map (cuda): from a brick distance of FINE_LEVEL_BELOW on,
# it jumps by bricks.
FINE_DISTANCE_CAP = 4
FINE_LEVEL_BELOW = 4


def build_ops(
    jit: Callable[[Any], Any],
    jit_called: Callable[[Any], Any] | None = None,
    voxels: SimpleNamespace | None = None,
) -> SimpleNamespace:
    """The march functions on `voxels` (tsdf.voxel.build_ops(jit, jit_called) unless given):
    with `jit` the march's start, step and refinement and the per-pixel functions, which the cpu
    loop needs inlined at numba IR level (as calls that LLVM keeps, its raycast took 1.2-5x as
    long); with `jit_called` (default `jit`) the small scalar helpers, which LLVM inlines
    anyway, and the whole march of one ray (see tsdf.voxel.build_ops)."""
    jit_called = jit_called or jit
    voxels = voxels or voxel_ops.build_ops(jit, jit_called)
    sample_tsdf_at, gradient_normal = voxels.sample_tsdf_at, voxels.gradient_normal
    surface_colour_at = voxels.surface_colour_at

    @jit_called
    def axis_interval(o: float, d: float, inverse: float, lower: float, upper: float) -> tuple:
        """(t_min, t_max) of one slab [lower, upper] along one axis (infinite when parallel),
        for direction component d = 1 / inverse."""
        if d == 0:
            if o >= lower and o <= upper:
                return -np.inf, np.inf
            return np.inf, -np.inf
        t0 = (lower - o) * inverse
        t1 = (upper - o) * inverse
        return min(t0, t1), max(t0, t1)

    @jit_called
    def ray_span(
        origin: Any, direction: tuple, volume_origin: Any, voxel_size: float, n: int
    ) -> tuple:
        """(entry, exit): the ray parameters where the ray is inside the volume's sample box
        [0, N - 1]^3 (entry >= 0; empty when entry >= exit). Multiplies by the direction's
        inverse where the reference divides (within an ulp: a ray's samples move by ~1e-16 m;
        the divisions per ray cost the cpu raycast ~3 %)."""
        d0, d1, d2 = direction
        upper = (n - 1) * voxel_size
        i0, i1, i2 = inverse_or_zero(d0), inverse_or_zero(d1), inverse_or_zero(d2)
        lo0, hi0 = axis_interval(origin[0], d0, i0, volume_origin[0], volume_origin[0] + upper)
        lo1, hi1 = axis_interval(origin[1], d1, i1, volume_origin[1], volume_origin[1] + upper)
        lo2, hi2 = axis_interval(origin[2], d2, i2, volume_origin[2], volume_origin[2] + upper)
        return max(max(max(lo0, lo1), lo2), 0.0), min(min(hi0, hi1), hi2)

    @jit_called
    def zero_crossing(t0: float, f0: float, t1: float, f1: float) -> float:
        return t0 + (t1 - t0) * f0 / (f0 - f1)

    @jit
    def sample_along(
        tsdf_weight: Any,
        offsets: tuple,
        origin: Any,
        direction: tuple,
        t: float,
        volume_origin: Any,
        voxel_size: float,
    ) -> float:
        """sample_tsdf_at the ray point at t; `offsets` = the buffer's (o0, o1, o2)."""
        o0, o1, o2 = offsets
        cx, cy, cz = voxel_coordinates(origin, direction, t, volume_origin, voxel_size)
        return sample_tsdf_at(tsdf_weight, o0, o1, o2, cx, cy, cz)

    @jit
    def refine_crossing(
        tsdf_weight: Any,
        offsets: tuple,
        origin: Any,
        direction: tuple,
        before: tuple,
        after: tuple,
        volume_origin: Any,
        voxel_size: float,
    ) -> float:
        """The ray distance of the surface between samples `before` = (t0, F > 0) and `after`
        = (t1, F < 0): one secant step, then a second on whichever side the estimate falls
        (the reference's)."""
        t0, f0 = before
        t1, f1 = after
        estimate = zero_crossing(t0, f0, t1, f1)
        f = sample_along(
            tsdf_weight, offsets, origin, direction, estimate, volume_origin, voxel_size
        )
        if f > 0:
            return zero_crossing(estimate, f, t1, f1)
        if f < 0:
            return zero_crossing(t0, f0, estimate, f)
        return estimate

    @jit_called
    def fine_index(whole: int, n: int, last: int) -> int:
        """Fine brick of the lower corner voxel of a sample at voxel coordinate c (clamped as
        sample_tsdf_at clamps it), at most `last`, from whole = floor(c / FINE): floor(c) //
        FINE clamped to [0, (N - 2) // FINE] is floor(c / FINE) clamped the same way."""
        return min(max(int(whole), 0), min((n - 2) // FINE, last))

    @jit_called
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

    @jit_called
    def first_sample_outside(
        m: int, c: tuple, dc: tuple, inverse: tuple, lower: tuple, size: float
    ) -> int:
        """Index of the first sample after sample m (at voxel coordinates c, advancing dc per
        sample, inverse = 1 / dc, all (x, y, z)) that may lie outside the cube
        [lower, lower + size)^3; at least m + 1. Multiplications only: the margin of
        samples_to_leave keeps it conservative."""
        to_leave = min(
            min(
                samples_to_leave(c[0], dc[0], inverse[0], lower[0], lower[0] + size),
                samples_to_leave(c[1], dc[1], inverse[1], lower[1], lower[1] + size),
            ),
            samples_to_leave(c[2], dc[2], inverse[2], lower[2], lower[2] + size),
        )
        return m + max(int(math.floor(to_leave)) + 1, 1)

    @jit_called
    def inverse_or_zero(x: float) -> float:
        return 1.0 / x if x != 0 else 0.0

    @jit_called
    def march_ray(
        tsdf_weight: Any,
        offsets: tuple,
        empty: Any,
        fine_distance: Any,
        origin: Any,
        direction: tuple,
        volume_origin: Any,
        voxel_size: float,
        step: float,
        safe_until: float,
    ) -> float:
        """Ray parameter of the first + to - crossing (regula-falsi refined), NaN if none; the
        samples lie at entry + m step (kintinuous_ref.raycast.march), marched from the first
        sample at or past `safe_until` (cpu.raycast.near_starts': no sample before it can be
        negative, so they are skipped like those of a jump; 0 starts at the entry).

        Empty space is skipped exactly with a distance map at two levels. `empty` is the brick
        distance map of kintinuous_ref.raycast._empty_space (logical bricks of BRICK^3 voxels):
        no sample in the cube of bricks within D - 1 of a brick at distance D can be negative,
        as there. `fine_distance` is finer, over FINE^3 bricks: fine_distance[f] = D >= 1 says
        no fine brick within chessboard distance D - 1 of f is `near` (may hold the lower
        corner of a negative sample), so every sample whose lower corner lies in that cube is
        >= 0 or unknown and, unless the sample before the first of them was negative, is
        skipped at once. The brick map is read only where the fine distance is capped at
        FINE_DISTANCE_CAP, or the fine map is a (1, 1, 1) one of 0, and used from a distance
        of FINE_LEVEL_BELOW on. Maps of shape (1, 1, 1) holding 0 skip nothing: the plain
        march. Jump lengths come from the samples' nominal coordinates (linear in the sample
        index) with a margin, so the samples skipped are a subset of those the exact test
        would skip: the same answer.
        The march is march_start, then march_step until it says the ray is done, then
        surface_at.
        """
        n = tsdf_weight.shape[0]
        ray = march_start(origin, direction, volume_origin, voxel_size, n, step, safe_until)
        m, previous, previous_known, crossing, value = ray[0], np.nan, ray[0] == 0, np.nan, 0.0
        while m >= 0:
            m, previous, previous_known, crossing, value = march_step(
                tsdf_weight,
                offsets,
                empty,
                fine_distance,
                origin,
                direction,
                volume_origin,
                voxel_size,
                step,
                ray,
                (m, previous, previous_known),
            )
        return surface_at(
            tsdf_weight,
            offsets,
            origin,
            direction,
            (crossing, value),
            previous,
            step,
            volume_origin,
            voxel_size,
        )

    @jit
    def surface_at(
        tsdf_weight: Any,
        offsets: tuple,
        origin: Any,
        direction: tuple,
        sample: tuple,
        before: float,
        step: float,
        volume_origin: Any,
        voxel_size: float,
    ) -> float:
        """The refined surface of a ray whose march found F = `before` > 0 at crossing - step
        and F < 0 at `sample` = (crossing, F) (crossing NaN: no crossing, no surface)."""
        crossing = sample[0]
        if not math.isfinite(crossing):
            return np.nan
        return refine_crossing(
            tsdf_weight,
            offsets,
            origin,
            direction,
            (crossing - step, before),
            sample,
            volume_origin,
            voxel_size,
        )

    @jit
    def march_start(
        origin: Any,
        direction: tuple,
        volume_origin: Any,
        voxel_size: float,
        n: int,
        step: float,
        safe_until: float,
    ) -> tuple:
        """(m, entry, exit, sx, sy, sz, dcx, dcy, dcz, ix, iy, iz) of a skipping march: the first
        sample m to look at (-1: the ray has none), the ray's span in the volume, the voxel
        coordinates of sample 0, their advance per sample and its inverses (0 where none)."""
        d0, d1, d2 = direction
        entry, exit_ = ray_span(origin, direction, volume_origin, voxel_size, n)
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
        voxels_per_step = step / voxel_size
        sx, sy, sz = voxel_coordinates(origin, direction, entry, volume_origin, voxel_size)
        dcx, dcy, dcz = d0 * voxels_per_step, d1 * voxels_per_step, d2 * voxels_per_step
        return (
            m,
            entry,
            exit_,
            sx,
            sy,
            sz,
            dcx,
            dcy,
            dcz,
            # 1 / dc, from the direction's inverses that ray_span takes too (one division each)
            inverse_or_zero(d0) * (voxel_size / step),
            inverse_or_zero(d1) * (voxel_size / step),
            inverse_or_zero(d2) * (voxel_size / step),
        )

    @jit
    def march_step(
        tsdf_weight: Any,
        offsets: tuple,
        empty: Any,
        fine_distance: Any,
        origin: Any,
        direction: tuple,
        volume_origin: Any,
        voxel_size: float,
        step: float,
        ray: tuple,
        state: tuple,
    ) -> tuple:
        """One step of march_ray from `state` = (sample m, previous F, whether it is known): a
        jump or a sample (`empty`, `fine_distance`: march_ray's maps; `ray`: march_start's).
        Returns (m, previous, previous_known, crossing, value) for the next step; m = -1 once
        the ray is done, and then crossing is the ray parameter of the sample past a + to -
        crossing, value its F and previous the F before it (surface_at refines them), or NaN:
        no surface."""
        m, previous, previous_known = state
        entry, exit_ = ray[1], ray[2]
        t = entry + m * step
        # The maps are read, and the sample taken, at the nominal coordinates (one
        # multiply-add, no division). They differ from the exact ones (the reference's) by
        # rounding only, so they name the same brick and fine brick unless within JUMP_MARGIN
        # of a fine brick's face: there the exact ones decide.
        cx, cy, cz = ray[3] + m * ray[6], ray[4] + m * ray[7], ray[5] + m * ray[8]
        wx, wy, wz = whole_fine(cx), whole_fine(cy), whole_fine(cz)
        if not (clear_of_faces(cx, wx) and clear_of_faces(cy, wy) and clear_of_faces(cz, wz)):
            cx, cy, cz = voxel_coordinates(origin, direction, t, volume_origin, voxel_size)
            wx, wy, wz = whole_fine(cx), whole_fine(cy), whole_fine(cz)
        # The fine map first: near surfaces, where most steps are, the brick map has nothing to
        # add, and one dependent load less per step made the cpu raycast ~4% faster.
        fine, fx, fy, fz = 0, 0, 0, 0
        last_fine = fine_distance.shape[0] - 1
        if not (previous_known and previous < 0):
            n = tsdf_weight.shape[0]
            fx = fine_index(wx, n, last_fine)
            fy = fine_index(wy, n, last_fine)
            fz = fine_index(wz, n, last_fine)
            fine = int(fine_distance[fx, fy, fz])
        radius, bx, by, bz = 0, 0, 0, 0
        if last_fine == 0 or fine >= FINE_DISTANCE_CAP:
            bricks = empty.shape[0]
            bx = min(max(int(math.floor(cx / BRICK)), 0), bricks - 1)
            by = min(max(int(math.floor(cy / BRICK)), 0), bricks - 1)
            bz = min(max(int(math.floor(cz / BRICK)), 0), bricks - 1)
            radius = int(empty[bx, by, bz])
        advance, inverse = (ray[6], ray[7], ray[8]), (ray[9], ray[10], ray[11])
        if radius >= FINE_LEVEL_BELOW:  # far from surfaces: past the empty cube of bricks
            reach = radius - 1
            lower = ((bx - reach) * BRICK, (by - reach) * BRICK, (bz - reach) * BRICK)
            m_next = first_sample_outside(
                m, (cx, cy, cz), advance, inverse, lower, (2 * reach + 1) * BRICK
            )
            previous_known = False
        elif fine > 0:  # no sample in the cube of fine bricks can be negative: jump past it
            reach = fine - 1
            lower = ((fx - reach) * FINE, (fy - reach) * FINE, (fz - reach) * FINE)
            m_next = first_sample_outside(
                m, (cx, cy, cz), advance, inverse, lower, (2 * reach + 1) * FINE
            )
            previous_known = False
        else:
            # (~1e-13 voxels from the reference's sample, a change in F far below its float32
            # output; recomputing the exact coordinates cost the cpu raycast ~2.5 %)
            value = sample_tsdf_at(tsdf_weight, offsets[0], offsets[1], offsets[2], cx, cy, cz)
            # A skipped sample is >= 0 or unknown, so after a jump the one before matters
            # only if this one is negative (a crossing, never a back face): fetched then.
            if not previous_known and value < 0:
                previous = np.nan
                if m > 0:
                    before = entry + (m - 1) * step
                    previous = sample_along(
                        tsdf_weight, offsets, origin, direction, before, volume_origin, voxel_size
                    )
            elif not previous_known:
                previous = np.nan
            if previous > 0 and value < 0:
                return -1, previous, True, t, value
            if previous < 0 and value > 0:
                return -1, previous, True, np.nan, np.nan  # a back face
            previous = value
            previous_known = True
            m_next = m + 1
        if not entry + m_next * step <= exit_:
            return -1, previous, previous_known, np.nan, np.nan
        return m_next, previous, previous_known, np.nan, np.nan

    @jit_called
    def whole_fine(c: float) -> int:
        """floor(c / FINE): the fine brick of coordinate c, unclamped."""
        return math.floor(c * (1.0 / FINE))

    @jit_called
    def clear_of_faces(c: float, whole: int) -> bool:
        """Whether coordinate c (whole = whole_fine(c)) is more than JUMP_MARGIN voxels from
        every fine brick face."""
        f = c * (1.0 / FINE) - whole
        return f >= JUMP_MARGIN / FINE and f <= 1.0 - JUMP_MARGIN / FINE

    @jit_called
    def voxel_coordinates(
        origin: Any, direction: tuple, t: float, volume_origin: Any, voxel_size: float
    ) -> tuple:
        """Continuous voxel coordinates of the ray point at t (sample_along's). The reference
        divides by the voxel size; a multiply by its inverse (within an ulp of the quotient)
        keeps the division's latency out of every sample: the cpu raycast ~3 % faster."""
        inverse = 1.0 / voxel_size
        cx = (origin[0] + t * direction[0] - volume_origin[0]) * inverse
        cy = (origin[1] + t * direction[1] - volume_origin[1]) * inverse
        cz = (origin[2] + t * direction[2] - volume_origin[2]) * inverse
        return cx, cy, cz

    @jit_called
    def ray_direction(u: int, v: int, camera: Any, rotation: Any) -> tuple:
        """Unit world-frame direction of pixel (u, v)'s ray (`camera` float64 fx, fy, cx, cy)."""
        rx = (u - camera[2]) * 1.0 / camera[0]
        ry = (v - camera[3]) * 1.0 / camera[1]
        d0 = rotation[0, 0] * rx + rotation[0, 1] * ry + rotation[0, 2]
        d1 = rotation[1, 0] * rx + rotation[1, 1] * ry + rotation[1, 2]
        d2 = rotation[2, 0] * rx + rotation[2, 1] * ry + rotation[2, 2]
        scale = 1.0 / math.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
        return d0 * scale, d1 * scale, d2 * scale

    @jit
    def raycast_pixel(
        tsdf_weight: Any,
        colour_volume: Any,
        has_colour: bool,
        offsets: tuple,
        empty: Any,
        fine_distance: Any,
        pixel: tuple,
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
    ) -> None:
        """Vertex, normal and colour of `pixel` = (u, v) (kintinuous_ref.raycast.raycast) by
        march_ray from `safe_until` on (0: from where the ray enters the volume). `camera` is
        float64 (fx, fy, cx, cy). Every pixel cast is
        written, hit or miss, so the caller clears only the pixels a stride leaves out."""
        d = ray_direction(pixel[0], pixel[1], camera, rotation)
        t = march_ray(
            tsdf_weight,
            offsets,
            empty,
            fine_distance,
            origin,
            d,
            volume_origin,
            voxel_size,
            step,
            safe_until,
        )
        shade_pixel(
            tsdf_weight,
            colour_volume,
            has_colour,
            offsets,
            pixel,
            t,
            origin,
            d,
            volume_origin,
            voxel_size,
            vertices,
            normals,
            colours,
        )

    @jit
    def shade_pixel(
        tsdf_weight: Any,
        colour_volume: Any,
        has_colour: bool,
        offsets: tuple,
        pixel: tuple,
        t: float,
        origin: Any,
        direction: tuple,
        volume_origin: Any,
        voxel_size: float,
        vertices: Any,
        normals: Any,
        colours: Any,
    ) -> None:
        """Vertex, normal and colour of `pixel` = (u, v) whose ray met the surface at t (NaN:
        none)."""
        if not math.isfinite(t):
            store_miss(pixel, vertices, normals, colours)
            return
        o0, o1, o2 = offsets
        point = voxel_coordinates(origin, direction, t, volume_origin, voxel_size)
        normal = gradient_normal(tsdf_weight, o0, o1, o2, point[0], point[1], point[2])
        store_hit(
            colour_volume,
            has_colour,
            offsets,
            pixel,
            t,
            origin,
            direction,
            point,
            normal,
            vertices,
            normals,
            colours,
        )

    @jit
    def store_hit(
        colour_volume: Any,
        has_colour: bool,
        offsets: tuple,
        pixel: tuple,
        t: float,
        origin: Any,
        direction: tuple,
        point: tuple,
        normal: tuple,
        vertices: Any,
        normals: Any,
        colours: Any,
    ) -> None:
        """Writes `pixel` = (u, v)'s vertex (the ray point at t), normal and colour (at voxel
        coordinates `point`; black without `has_colour`); a miss when the normal is NaN (no use
        to ICP: dropped)."""
        if math.isnan(normal[0]):
            store_miss(pixel, vertices, normals, colours)
            return
        u, v = pixel
        vertices[v, u, 0] = origin[0] + t * direction[0]
        vertices[v, u, 1] = origin[1] + t * direction[1]
        vertices[v, u, 2] = origin[2] + t * direction[2]
        normals[v, u, 0], normals[v, u, 1], normals[v, u, 2] = normal
        r, g, b = 0, 0, 0
        if has_colour:
            o0, o1, o2 = offsets
            r, g, b = surface_colour_at(colour_volume, o0, o1, o2, point[0], point[1], point[2])
        colours[v, u, 0], colours[v, u, 1], colours[v, u, 2] = r, g, b

    @jit
    def store_miss(pixel: tuple, vertices: Any, normals: Any, colours: Any) -> None:
        """Writes `pixel` = (u, v) as seeing no surface: NaN vertex and normal, black."""
        u, v = pixel
        for c in range(3):
            vertices[v, u, c] = np.nan
            normals[v, u, c] = np.nan
            colours[v, u, c] = 0

    return SimpleNamespace(
        axis_interval=axis_interval,
        clear_of_faces=clear_of_faces,
        fine_index=fine_index,
        first_sample_outside=first_sample_outside,
        inverse_or_zero=inverse_or_zero,
        march_ray=march_ray,
        march_start=march_start,
        march_step=march_step,
        ray_direction=ray_direction,
        ray_span=ray_span,
        raycast_pixel=raycast_pixel,
        refine_crossing=refine_crossing,
        sample_along=sample_along,
        samples_to_leave=samples_to_leave,
        shade_pixel=shade_pixel,
        store_hit=store_hit,
        surface_at=surface_at,
        store_miss=store_miss,
        voxel_coordinates=voxel_coordinates,
        whole_fine=whole_fine,
        zero_crossing=zero_crossing,
    )
