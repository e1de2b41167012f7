"""Per-ray maths of kintinuous_ref.raycast, written once for the CPU and the CUDA target: the
march along a ray with exact empty-space skipping (brick and fine distance maps), the
regula-falsi refinement of the crossing, and (raycast.shading) the vertex, TSDF-gradient normal
and colour of the hit, from the voxel functions of kintinuous_fast.tsdf.voxel and the ray
geometry of raycast.ray.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from types import SimpleNamespace
from typing import Any

import numpy as np

from kintinuous_fast.raycast.ray import build_jumps, build_ray
from kintinuous_fast.raycast.shading import build_pixel, build_shading
from kintinuous_fast.tsdf import voxel as voxel_ops
from kintinuous_fast.tsdf.voxel import BRICK, FINE

# The cpu raycast's fine distance map (in FINE^3 bricks) is capped here: a jump then leaves a
# cube reaching at most 3 fine bricks (6 voxels) to either side. Rays start where they enter
# the first fine brick that may hold a negative sample (raycast.cpu_near_starts), so long fine
# jumps are rare, while each step of the cap costs the map two more passes (docs/benchmarks.md,
# "Numbers behind the fast stages"). A step reads the fine map first (near surfaces its jumps
# are longer than the brick map's, whose cube of radius D - 1 is a single brick at D = 1) and
# the brick map only where the fine distance is capped, or where there is no fine map (cuda):
# from a brick distance of FINE_LEVEL_BELOW on, it jumps by bricks.
FINE_DISTANCE_CAP = 4
FINE_LEVEL_BELOW = 4


def build_ops(
    jit: Callable[[Any], Any],
    jit_called: Callable[[Any], Any] | None = None,
    voxels: SimpleNamespace | None = None,
) -> SimpleNamespace:
    """The march functions on `voxels` (tsdf.voxel.build_ops(jit, jit_called) unless given): with
    `jit` the march's start, step and refinement and the per-pixel functions, which the cpu loop
    needs inlined at numba IR level (as calls that LLVM keeps, its raycast is slower:
    docs/benchmarks.md, "Numbers behind the fast stages"); with `jit_called` (default `jit`) the
    small scalar helpers, which LLVM inlines anyway, and the whole march of one ray (see
    tsdf.voxel.build_ops). One namespace of every function of the factories below."""
    jit_called = jit_called or jit
    voxels = voxels or voxel_ops.build_ops(jit, jit_called)
    ray_ops, jump_ops = build_ray(jit_called), build_jumps(jit_called)
    crossing_ops = _build_crossing(jit, voxels, ray_ops)
    step_ops = _build_march_step(jit, voxels, ray_ops, jump_ops, crossing_ops)
    start_ops = _build_march_start(jit, ray_ops)
    march_ops = _build_march(jit_called, start_ops, step_ops, crossing_ops)
    shading_ops = build_shading(jit, voxels, ray_ops)
    pixel_ops = build_pixel(jit, ray_ops, march_ops, shading_ops)
    parts = (ray_ops, jump_ops, crossing_ops, step_ops, start_ops, march_ops, shading_ops)
    parts += (pixel_ops,)
    return SimpleNamespace(**{name: f for part in parts for name, f in vars(part).items()})


def _build_crossing(
    jit: Callable[[Any], Any], voxels: SimpleNamespace, ray_ops: SimpleNamespace
) -> SimpleNamespace:
    """A sample along a ray, and the refined surface between the two samples of a crossing."""
    sample_tsdf_at = voxels.sample_tsdf_at
    voxel_coordinates, zero_crossing = ray_ops.voxel_coordinates, ray_ops.zero_crossing

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

    return SimpleNamespace(
        refine_crossing=refine_crossing, sample_along=sample_along, surface_at=surface_at
    )


def _build_march_start(jit: Callable[[Any], Any], ray_ops: SimpleNamespace) -> SimpleNamespace:
    """The set-up of one ray's skipping march."""
    ray_span, voxel_coordinates = ray_ops.ray_span, ray_ops.voxel_coordinates
    inverse_or_zero = ray_ops.inverse_or_zero

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

    return SimpleNamespace(march_start=march_start)


def _build_march_step(
    jit: Callable[[Any], Any],
    voxels: SimpleNamespace,
    ray_ops: SimpleNamespace,
    jump_ops: SimpleNamespace,
    crossing_ops: SimpleNamespace,
) -> SimpleNamespace:
    """One step of a ray's march: a jump over empty space, or a sample."""
    sample_tsdf_at, voxel_coordinates = voxels.sample_tsdf_at, ray_ops.voxel_coordinates
    whole_fine, clear_of_faces = jump_ops.whole_fine, jump_ops.clear_of_faces
    fine_index, first_sample_outside = jump_ops.fine_index, jump_ops.first_sample_outside
    sample_along = crossing_ops.sample_along

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
        # add, and the brick map's load would be one more dependent load per step.
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
            # output; recomputing the exact coordinates at every sample costs more)
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

    return SimpleNamespace(march_step=march_step)


def _build_march(
    jit_called: Callable[[Any], Any],
    start_ops: SimpleNamespace,
    step_ops: SimpleNamespace,
    crossing_ops: SimpleNamespace,
) -> SimpleNamespace:
    """The whole march of one ray: its start, its steps, the refined crossing."""
    march_start, march_step = start_ops.march_start, step_ops.march_step
    surface_at = crossing_ops.surface_at

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
        samples lie at entry + m step (kintinuous_ref.raycast._march), marched from the first
        sample at or past `safe_until` (raycast.cpu_near_starts': no sample before it can be
        negative, so they are skipped like those of a jump; 0 starts at the entry).

        Empty space is skipped exactly with a distance map at two levels. `empty` is the brick
        distance map of kintinuous_ref.raycast.empty_space (logical bricks of BRICK^3 voxels):
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

    return SimpleNamespace(march_ray=march_ray)
