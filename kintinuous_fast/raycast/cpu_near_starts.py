# ruff: noqa: ANN001, ANN201  (numba loops: argument types come from the call)
"""Where each ray of the cpu raycast starts: the least distance at which it enters a fine brick
that may hold a negative sample (near_starts: slab tests against those bricks' boxes over their
projections). No sample before it can be negative, so starting there skips the same samples as
the march's own jumps: the same answer.
"""

from __future__ import annotations

import functools
import math

import numba
import numpy as np

from kintinuous_fast.raycast.cpu_ops import OPS
from kintinuous_fast.targets.cpu import (
    atomic_fetch_add,
    claim_slot,
    claimed_items,
    parallel_part,
    run_parallel,
)
from kintinuous_fast.tsdf.volume import FastTsdfVolume, view_constants
from kintinuous_fast.tsdf.voxel import FINE
from kintinuous_ref.camera import Intrinsics

ray_direction = OPS.ray_direction
# near_starts' slab tests in float32: the boxes grow by ENTRY_MARGIN metres on every side and a
# ray's entry shrinks by ENTRY_SLACK of itself, so that rounding never makes a start late.
ENTRY_MARGIN = 1e-5
ENTRY_SLACK = 1e-6
NEAR_BLOCK = 16  # near_starts looks for the next run of near bricks this many at a time
# Runs of adjacent slabs per thread that near_starts' threads claim one at a time: with a fixed
# share of the slabs each, a thread whose slabs held more surface kept the others waiting
# (0.5-0.6 ms of 4.9-5.0 on two threads; 0.06-0.07 ms with eight runs a thread).
SLAB_PARTS_PER_THREAD = 8


@parallel_part(error_model="numpy", _nrt=True)
def _near_box_starts(
    claims,
    parts,
    near,
    camera,
    rotation,
    origin,
    volume_origin,
    voxel_size,
    inverse,
    longest,
    starts,
    used,
):
    """Each thread's image starts[t] = per pixel, the least ray distance at which the pixel's
    ray enters a box of the `near` fine bricks of the slabs it claims (runs of adjacent slabs,
    `parts` of them), inf where it enters none; `used[0]` (zero before the call) counts the
    threads, whose images near_starts' minimum reads. A minimum is exact in any order, so
    which thread paints which slabs changes nothing; many parts even out the threads' work,
    and adjacent slabs paint nearby pixels, whose ray directions are still in the cache.
    `inverse` (3, H, W): 1 / the rays' unit directions. Runs of up to `longest` near bricks
    along k are taken as one box (the same answer: the ray enters their union where it enters
    the first of them)."""
    m = near.shape[0]
    image = starts[claim_slot(claims)]
    image[:] = np.inf
    atomic_fetch_add(used, 0)
    size = FINE * voxel_size
    # Camera-frame corner of the volume and camera-frame steps of one fine brick along each axis.
    offset = np.empty(3)
    steps = np.empty((3, 3))
    for r in range(3):
        offset[r] = (
            rotation[0, r] * (volume_origin[0] - origin[0])
            + rotation[1, r] * (volume_origin[1] - origin[1])
            + rotation[2, r] * (volume_origin[2] - origin[2])
        )
        for axis in range(3):
            steps[axis, r] = rotation[axis, r] * size
    for i in claimed_items(claims, m, parts):
        for j in range(m):
            row = near[i, j]
            if not _any(row, 0, m):  # most rows: one vectorised OR, no byte-by-byte scan
                continue
            k = _next_near(row, 0)
            while k < m:  # each run of near bricks along k is one box
                end = k + 1
                while end < min(m, k + longest) and row[end]:
                    end += 1
                run = (i, j, k, end - k)
                _paint_box(run, offset, steps, camera, origin, volume_origin, size, inverse, image)
                k = _next_near(row, end)


@numba.njit(cache=True, inline="always")
def _any(row, start, stop):
    """Whether any of row[start:stop] is True (an OR over the block, vectorised)."""
    seen = False
    for k in range(start, stop):
        seen |= row[k]
    return seen


@numba.njit(cache=True, inline="always")
def _next_near(row, k):
    """The first index >= k of a True entry of `row` (its length if none), passing over
    aligned blocks of NEAR_BLOCK entries that hold none."""
    m = row.shape[0]
    while k < m:
        if k % NEAR_BLOCK == 0 and k + NEAR_BLOCK <= m and not _any(row, k, k + NEAR_BLOCK):
            k += NEAR_BLOCK
        elif row[k]:
            return k
        else:
            k += 1
    return m


@numba.njit(cache=True, error_model="numpy", inline="always")
def _paint_box(bricks, offset, steps, camera, origin, volume_origin, size, inverse, start):
    """start = min(start, where the pixel's ray enters the box of fine bricks (i, j, k) ..
    (i, j, k + run - 1), `bricks` = (i, j, k, run)) over the pixels of the bounding box of its
    projection, grown by half a pixel (the whole image when the box reaches behind the camera's
    plane; nothing when it lies wholly behind), whose rays meet the box."""
    i, j, k, run = bricks
    height, width = start.shape
    u_lo, u_hi, v_lo, v_hi = np.inf, -np.inf, np.inf, -np.inf
    behind = 0
    for a in range(2):
        for b in range(2):
            for d in range(2):
                x = (
                    offset[0]
                    + (i + a) * steps[0, 0]
                    + (j + b) * steps[1, 0]
                    + (k + d * run) * steps[2, 0]
                )
                y = (
                    offset[1]
                    + (i + a) * steps[0, 1]
                    + (j + b) * steps[1, 1]
                    + (k + d * run) * steps[2, 1]
                )
                z = (
                    offset[2]
                    + (i + a) * steps[0, 2]
                    + (j + b) * steps[1, 2]
                    + (k + d * run) * steps[2, 2]
                )
                if not z > 0:
                    behind += 1
                    continue
                u = camera[0] * x / z + camera[2]
                v = camera[1] * y / z + camera[3]
                u_lo, u_hi = min(u_lo, u), max(u_hi, u)
                v_lo, v_hi = min(v_lo, v), max(v_hi, v)
    if behind == 8:
        return
    u0, u1, v0, v1 = 0, width - 1, 0, height - 1
    if behind == 0:
        u0 = max(int(math.floor(u_lo - 0.5)), 0)
        u1 = min(int(math.ceil(u_hi + 0.5)), width - 1)
        v0 = max(int(math.floor(v_lo - 0.5)), 0)
        v1 = min(int(math.ceil(v_hi + 0.5)), height - 1)
    # The box's faces relative to the camera, grown by ENTRY_MARGIN so that rounding in the
    # slab test never misses a ray that touches it; a ray's slab distances are these times its
    # inverse direction.
    low = (
        np.float32(volume_origin[0] + i * size - origin[0] - ENTRY_MARGIN),
        np.float32(volume_origin[1] + j * size - origin[1] - ENTRY_MARGIN),
        np.float32(volume_origin[2] + k * size - origin[2] - ENTRY_MARGIN),
    )
    sides = (np.float32(size + 2.0 * ENTRY_MARGIN), np.float32(run * size + 2.0 * ENTRY_MARGIN))
    for v in range(v0, v1 + 1):
        columns = slice(u0, u1 + 1)
        _enter_row(
            low,
            sides,
            inverse[0, v, columns],
            inverse[1, v, columns],
            inverse[2, v, columns],
            start[v, columns],
        )


@numba.njit(cache=True, error_model="numpy", inline="always")
def _enter_row(low, sides, inverse0, inverse1, inverse2, line):
    """line = min(line, the ray distance where each ray enters the box from `low` (camera at
    0) with sides size, size, length (`sides` = (size, length)), less the slack) over the rays
    that meet it at t >= 0 (slab test; branch free, so the loop vectorises)."""
    low0, low1, low2 = low
    size, length = sides
    for u in range(line.shape[0]):
        a0, b0 = low0 * inverse0[u], (low0 + size) * inverse0[u]
        a1, b1 = low1 * inverse1[u], (low1 + size) * inverse1[u]
        a2, b2 = low2 * inverse2[u], (low2 + length) * inverse2[u]
        enter = max(max(min(a0, b0), min(a1, b1)), max(min(a2, b2), np.float32(0.0)))
        leave = min(min(max(a0, b0), max(a1, b1)), max(a2, b2))
        bound = enter * np.float32(1.0 - ENTRY_SLACK)
        line[u] = min(line[u], bound if enter <= leave else np.float32(np.inf))


@parallel_part()
def _least_over_images(claims, parts, starts, used, out):
    """out = the per-pixel minimum of the first used[0] images of `starts`."""
    images = min(used[0], starts.shape[0])
    for v in claimed_items(claims, out.shape[0], parts):
        for u in range(out.shape[1]):
            least = starts[0, v, u]
            for t in range(1, images):
                least = min(least, starts[t, v, u])
            out[v, u] = least


@parallel_part(error_model="numpy")
def _inverse_directions(claims, parts, camera, rotation, out):
    """out[:, v, u] = 1 / the unit direction of pixel (u, v)'s ray (raycast.ops.ray_direction),
    1e30 for a component within 1e-30 of zero (its slab then bounds nothing, or everything, as
    it should; float32 holds it)."""
    for v in claimed_items(claims, out.shape[1], parts):
        for u in range(out.shape[2]):
            d = ray_direction(u, v, camera, rotation)
            for axis in range(3):
                out[axis, v, u] = 1.0 / d[axis] if abs(d[axis]) > 1e-30 else 1e30


@functools.lru_cache(maxsize=2)
def _thread_starts(threads: int, height: int, width: int) -> np.ndarray:
    """near_starts' per-thread images, kept from frame to frame (fresh ones cost page faults)."""
    return np.empty((threads, height, width), dtype=np.float32)


@functools.lru_cache(maxsize=2)
def _inverse_directions_work(height: int, width: int) -> np.ndarray:
    """near_starts' inverse ray directions (3, H, W), kept from frame to frame."""
    return np.empty((3, height, width), dtype=np.float32)


def near_starts(
    volume: FastTsdfVolume, near: np.ndarray, pose: np.ndarray, camera: Intrinsics
) -> np.ndarray:
    """Per pixel, a ray distance before which no sample of its ray can be negative (inf: none
    can), from the `near` map of fine bricks (skip_maps').

    A sample can be negative only if the fine brick of its lower corner voxel is near, and a
    sample lies in the closed box of that fine brick ([2f, 2f + 2] voxels per axis, clamping
    included). So none before the ray first enters a near box can be, and a jump to there
    skips the same samples as the march's own jumps: the same answer. Each near box (a run of
    them along the line of sight as one) is projected into the image, and the pixels of its
    projected bounds, grown by half a pixel, take where their rays enter it (a slab test in
    float32 against the box grown by ENTRY_MARGIN, less ENTRY_SLACK of the distance: both far
    above float32's rounding of coordinates within ~100 m, far below a sample step). Where a
    ray enters a box, not the camera's distance to it, leaves the fewest jumps after the start
    (docs/benchmarks.md, "Numbers behind the fast stages")."""
    images = _thread_starts(numba.get_num_threads(), camera.height, camera.width)
    view = view_constants(volume, pose, camera)
    inverse = _inverse_directions_work(camera.height, camera.width)
    run_parallel(_inverse_directions, view[0], view[1], inverse)
    # A run of boxes along the line of sight projects to about one box's pixels, a run across
    # it to a long slanted one (about twice the pixels of its boxes).
    rotation = view[1]
    along_sight = abs(rotation[2, 2]) >= max(abs(rotation[0, 2]), abs(rotation[1, 2]))
    longest = near.shape[0] if along_sight else 1
    used = np.zeros(1, dtype=np.int64)
    parts = SLAB_PARTS_PER_THREAD * len(images)
    run_parallel(_near_box_starts, near, *view, inverse, longest, images, used, parts=parts)
    starts = np.empty((camera.height, camera.width), dtype=np.float64)
    run_parallel(_least_over_images, images, used, starts)
    return starts
