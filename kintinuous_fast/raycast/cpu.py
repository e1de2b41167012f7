# ruff: noqa: ANN001, ANN201  (numba kernels and loops: argument types come from the call)
"""kintinuous_ref.raycast on the CPU: a loop over bands of pixel rows (on all threads) around
kintinuous_fast.raycast.ops, with the reference's exact brick empty-space skipping plus a finer
second level inside the bricks next to a surface. Each ray starts where it first enters a fine
brick that may hold a negative sample (near_starts: slab tests against those bricks' boxes over
their projections), and rays go on from there two at a time, in lockstep
(march_two_rays below). Every skip is exact: the maps are the plain march's.

Both levels come from the per-fine-brick bit masks of observed negative voxels that
integration keeps up to date (kintinuous_fast.tsdf.cpu.negative_masks), so no frame scans the
volume: the brick map of kintinuous_ref.raycast._empty_space is the chessboard distance over the
8^3 bricks holding a marked voxel, and the fine map marks the fine bricks holding the lower
corner of a sample that may be negative.
"""

from __future__ import annotations

import functools
import math
from types import SimpleNamespace
from typing import Any

import numba
import numpy as np

from kintinuous_fast.raycast import ops as march
from kintinuous_fast.raycast.ops import FINE_DISTANCE_CAP
from kintinuous_fast.targets import cpu_jit_numpy_errors, cpu_jit_numpy_errors_called
from kintinuous_fast.targets.cpu import claimed_items, parallel_part, run_parallel
from kintinuous_fast.tsdf import voxel as volume
from kintinuous_fast.tsdf.cpu import negative_masks
from kintinuous_fast.tsdf.volume import FastTsdfVolume
from kintinuous_fast.tsdf.voxel import BRICK, FINE
from kintinuous_ref.camera import Intrinsics
from kintinuous_ref.raycast import STEP_FRACTION, ModelPrediction, check_stride

__all__ = ["STEP_FRACTION", "ModelPrediction", "empty_space", "raycast"]

_voxels = volume.build_ops(cpu_jit_numpy_errors, cpu_jit_numpy_errors_called, dequantise_table=True)
_ops = march.build_ops(cpu_jit_numpy_errors, cpu_jit_numpy_errors_called, _voxels)
# The shared per-ray functions this file builds on, as globals numba can call.
march_start, march_step, surface_at = _ops.march_start, _ops.march_step, _ops.surface_at
raycast_pixel, ray_direction, shade_pixel = _ops.raycast_pixel, _ops.ray_direction, _ops.shade_pixel
voxel_coordinates, store_hit = _ops.voxel_coordinates, _ops.store_hit
gradient_normals = _voxels.gradient_normals
BAND = 8  # pixel rows handed to a thread at a time
# near_starts' slab tests in float32: the boxes grow by ENTRY_MARGIN metres on every side and a
# ray's entry shrinks by ENTRY_SLACK of itself, so that rounding never makes a start late.
ENTRY_MARGIN = 1e-5
ENTRY_SLACK = 1e-6
NEAR_BLOCK = 16  # near_starts looks for the next run of near bricks this many at a time


# Bits of a fine brick's mask (tsdf.voxel.fine_voxel_bit: 4 a + 2 b + c for voxel (a, b, c)
# of the brick) at c = 0, and at b = c = 0.
_AT_C0, _AT_B0_C0 = np.uint8(0b01010101), np.uint8(0b00010001)


# The maps of _brick_maps from the fine masks (M, M, M): near[f] = any marked voxel among
# voxels 2f .. 2f + 2 on every axis, the corners of the samples whose lower corner lies in fine
# brick f, and negative[b] = any marked voxel in 8^3 brick b (kintinuous_ref.raycast.
# _empty_space's). near comes from three separable passes: along k then j, a brick's voxels and
# the next brick's first fold into its bits at c = 0 (`rows`), then at b = c = 0 (`planes`);
# along i, the same decides `near`. Bytes are combined with | and &, so the loops have no
# branches and vectorise (each pass writes a fresh array: folding in place kept LLVM from
# vectorising, 13x slower).


@parallel_part(error_model="numpy")
def _fold_rows_and_planes(claims, parts, masks, rows, planes):
    """rows and planes of the slabs f0 of this part."""
    m = masks.shape[0]
    for f0 in claimed_items(claims, m, parts):
        for f1 in range(m):
            row = masks[f0, f1]
            _fold(row[: m - 1], row[1:], _AT_C0, 1, rows[f0, f1, : m - 1])
            _fold(row[m - 1 :], row[m - 1 :], _AT_C0, 1, rows[f0, f1, m - 1 :])  # no next
        for f1 in range(m):  # the last has no next: folding it with itself adds nothing
            _fold(rows[f0, f1], rows[f0, min(f1 + 1, m - 1)], _AT_B0_C0, 2, planes[f0, f1])


@parallel_part(error_model="numpy")
def _fold_slabs(claims, parts, planes, near):
    """near of the slabs f0 of this part, once every slab's planes are done."""
    m = planes.shape[0]
    for f0 in claimed_items(claims, m, parts):
        following = planes[min(f0 + 1, m - 1)]
        for f1 in range(m):
            _or_first(planes[f0, f1], following[f1], near[f0, f1])


@parallel_part(error_model="numpy", _nrt=True)
def _negative_bricks(claims, parts, masks, negative):
    """negative of the slabs of bricks b0 of this part."""
    m = masks.shape[0]
    per_brick = BRICK // FINE
    bricks = negative.shape[0]
    for b0 in claimed_items(claims, bricks, parts):
        # the slab's masks ORed over i and, per brick row, over j (vectorised); then over k
        seen = np.zeros((bricks, m), dtype=np.uint8)
        for f0 in range(b0 * per_brick, min((b0 + 1) * per_brick, m)):
            for f1 in range(m):
                _or_into(seen[f1 // per_brick], masks[f0, f1])
        for b1 in range(bricks):
            for b2 in range(bricks):
                any_marked = np.uint8(0)
                for f2 in range(b2 * per_brick, min((b2 + 1) * per_brick, m)):
                    any_marked |= seen[b1, f2]
                negative[b0, b1, b2] = any_marked != 0


@numba.njit(cache=True, inline="always")
def _or_into(target, source):
    """target |= source, elementwise over 1-d uint8 arrays (vectorised)."""
    for j in range(target.shape[0]):
        target[j] = target[j] | source[j]


@numba.njit(cache=True, inline="always")
def _fold(masks, following, first, shift, out):
    """out = the bits of `first` (a brick's voxels at 0 on this axis) set where the voxel or
    the one `shift` bits above it (at 1) is marked, or the following brick's voxel at 0 is,
    elementwise over 1-d uint8 arrays (vectorised). Folding a row with itself keeps it."""
    for j in range(out.shape[0]):
        both = masks[j] | (following[j] & first)
        out[j] = (both | (both >> shift)) & first


@numba.njit(cache=True, inline="always")
def _or_first(planes, following, near):
    """near = any bit of planes, or the first (a = b = c = 0) of following, elementwise."""
    for j in range(near.shape[0]):
        near[j] = (planes[j] | (following[j] & np.uint8(1))) != 0


@functools.lru_cache(maxsize=2)
def _work_arrays(fine_bricks: int, bricks: int) -> SimpleNamespace:
    """The skip maps' work arrays for one volume size, kept from frame to frame: at 256^3,
    fresh ones cost ~2 ms of page faults per frame (measured when the maps took ~6.5 ms)."""
    fine_shape, shape = (fine_bricks,) * 3, (bricks,) * 3
    return SimpleNamespace(
        rows=np.empty(fine_shape, dtype=np.uint8),
        planes=np.empty(fine_shape, dtype=np.uint8),
        near=np.empty(fine_shape, dtype=np.bool_),
        negative=np.empty(shape, dtype=np.bool_),
    )


def _brick_maps(volume: FastTsdfVolume) -> tuple[np.ndarray, SimpleNamespace]:
    """(empty, work): kintinuous_ref.raycast._empty_space of the volume (int64 brick distances)
    and the work arrays, whose `near` map of fine bricks (bool) skip_maps turns into distances,
    both from the negative-voxel masks."""
    masks = negative_masks(volume)
    work = _work_arrays(masks.shape[0], -(-volume.resolution // BRICK))
    run_parallel(_fold_rows_and_planes, masks, work.rows, work.planes)
    run_parallel(_fold_slabs, work.planes, work.near)
    run_parallel(_negative_bricks, masks, work.negative)
    return _brick_distance(work.negative), work


def _brick_distance(negative: np.ndarray) -> np.ndarray:
    """kintinuous_ref.raycast._empty_space from its (B, B, B) map of bricks holding an observed
    negative voxel (int64). Growing by one brick and then taking the chessboard distance is the
    chessboard distance less one, floored at 0; _capped_distance gives it with a cap (B + 1)
    that no distance inside the grid reaches (numba, ~0.1 ms at B = 32 where scipy's dilation
    and transform took ~1.4)."""
    b = negative.shape[0]
    if not negative.any():
        return np.full(negative.shape, 2 * b, dtype=np.int64)  # nothing anywhere: skip it all
    distance = _capped_distance(negative, b + 1)
    return np.maximum(distance.astype(np.int64) - 1, 0)


def _capped_distance(near: np.ndarray, cap: int) -> np.ndarray:
    """min(cap, chessboard distance to the nearest True of `near` (M, M, M)), uint8, cap < 255:
    a work array that the next call for the same size and cap overwrites."""
    out, result, work = _distance_work(near.shape[0], cap)
    run_parallel(_distance_along_rows, near, cap, result, work)
    run_parallel(_distance_along_columns, cap, result, work)
    run_parallel(_distance_along_slabs, cap, work, result, out)
    return out


@functools.lru_cache(maxsize=4)
def _distance_work(m: int, cap: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """_capped_distance's result and two work arrays for one size and cap, kept from frame to
    frame; the work arrays' rows are padded by cap - 1 on both sides (the passes below)."""
    padded = (m, m, m + 2 * (cap - 1))
    return (
        np.empty((m, m, m), dtype=np.uint8),
        np.empty(padded, dtype=np.uint8),
        np.empty(padded, dtype=np.uint8),
    )


# _capped_distance(near, cap) in three passes, by way of `result` and `work`, (M, M, M + 2 pad)
# with pad = cap - 1. Separable (the chessboard metric is the max of the per-axis distances, so
# the minimum can be taken one axis at a time): along each axis d(x) = min over |k| < cap of
# max(k, d(x + k e)), from 0 at near entries and cap elsewhere. Each pass is elementwise over
# whole planes of uint8, which vectorises: shifts by k entries (axis 2: rows padded with cap,
# which never lowers a minimum, so no row reads the next), by k rows (axis 1) and by k planes
# (axis 0). The passes may lower a pad; no entry reads one after the first pass. Shifting each
# row of 128 on its own cost more than the shifts: the fine map took 2.5 ms on one thread, 1.1
# with whole-plane shifts.


@parallel_part()
def _distance_along_rows(claims, parts, near, cap, result, work):
    """Axis 2: result from `near`, through the padded rows of `work`."""
    m = near.shape[0]
    pad = cap - 1
    row = m + 2 * pad
    top = np.uint8(cap)
    for p in claimed_items(claims, m, parts):
        plane = work[p]
        for f1 in range(m):
            plane[f1, :pad] = top
            plane[f1, pad + m :] = top
            _zero_at_near(near[p, f1], top, plane[f1, pad : pad + m])
        _shifted_min_max(plane.reshape(m * row), cap, result[p].reshape(m * row), 1)


@parallel_part()
def _distance_along_columns(claims, parts, cap, result, work):
    """Axis 1: work from result."""
    m, row = result.shape[0], result.shape[2]
    for p in claimed_items(claims, m, parts):
        _shifted_min_max(result[p].reshape(m * row), cap, work[p].reshape(m * row), row)


@parallel_part()
def _distance_along_slabs(claims, parts, cap, work, result, out):
    """Axis 0: result from work, and its unpadded rows into out."""
    m, row = work.shape[0], work.shape[2]
    pad = cap - 1
    for f0 in claimed_items(claims, m, parts):
        target = result[f0].reshape(m * row)
        _copy(work[f0].reshape(m * row), target)
        for k in range(1, min(cap, m)):
            for g in (f0 - k, f0 + k):
                if 0 <= g < m:
                    _min_max(target, work[g].reshape(m * row), np.uint8(k))
        for f1 in range(m):
            _copy(result[f0, f1, pad : pad + m], out[f0, f1])


@numba.njit(cache=True, inline="always")
def _copy(source, target):
    """target = source, elementwise over 1-d arrays (numba's slice assignment took 5x longer
    on rows of 128)."""
    for j in range(target.shape[0]):
        target[j] = source[j]


@numba.njit(cache=True, inline="always")
def _zero_at_near(near_row, top, row):
    """row = 0 where near_row, else top (vectorised select)."""
    for j in range(row.shape[0]):
        row[j] = np.uint8(0) if near_row[j] else top


@numba.njit(cache=True, inline="always")
def _shifted_min_max(source, cap, target, stride):
    """target = min over |k| < cap of max(k, source shifted by k strides), clipped at the
    ends (1-d uint8 arrays of the same length)."""
    n = source.shape[0]
    _copy(source, target)
    for k in range(1, cap):
        shift = k * stride
        if shift >= n:
            break
        _min_max(target[shift:], source[: n - shift], np.uint8(k))
        _min_max(target[: n - shift], source[shift:], np.uint8(k))


@numba.njit(cache=True, inline="always")
def _min_max(target, source, k):
    """target = min(target, max(k, source)), elementwise over 1-d uint8 arrays (vectorised)."""
    for j in range(target.shape[0]):
        target[j] = min(target[j], max(k, source[j]))


def skip_maps(volume: FastTsdfVolume) -> tuple[np.ndarray, np.ndarray]:
    """(empty, fine_distance): the brick distance map of _brick_maps and the capped distance
    map over its fine bricks (raycast.ops.march_ray's). The fine map is a work array: the next
    call for a volume of the same resolution overwrites it."""
    return _skip_maps_and_near(volume)[:2]


def _skip_maps_and_near(volume: FastTsdfVolume) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """skip_maps and the `near` map of fine bricks they come from (work arrays)."""
    empty, work = _brick_maps(volume)
    fine_distance = _capped_distance(work.near, FINE_DISTANCE_CAP)
    # uint8: the map stays in the first-level cache; a smaller distance only means shorter jumps
    return np.minimum(empty, 255).astype(np.uint8), fine_distance, work.near


def empty_space(volume: FastTsdfVolume) -> np.ndarray:
    """kintinuous_ref.raycast._empty_space of the fast volume (brick distance map, int64)."""
    return _brick_maps(volume)[0]


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
):
    """starts[c] = per pixel, the least ray distance at which the pixel's ray enters a box of
    the `near` fine bricks of slabs c, c + C, ... (C = starts.shape[0]), inf where it enters
    none: chunk c's part of near_starts. `inverse` (3, H, W): 1 / the rays' unit directions.
    Runs of up to `longest` near bricks along k are taken as one box (the same answer: the
    ray enters their union where it enters the first of them)."""
    chunks, height, width = starts.shape
    m = near.shape[0]
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
    for c in claimed_items(claims, chunks, parts):
        starts[c] = np.inf
        for i in range(c, m, chunks):  # slabs dealt round-robin: surfaces spread over them
            for j in range(m):
                row = near[i, j]
                if not _any(row, 0, m):  # most rows: scanning them byte by byte took ~1 ms
                    continue
                k = _next_near(row, 0)
                while k < m:  # each run of near bricks along k is one box
                    end = k + 1
                    while end < min(m, k + longest) and row[end]:
                        end += 1
                    run = (i, j, k, end - k)
                    _paint_box(
                        run, offset, steps, camera, origin, volume_origin, size, inverse, starts[c]
                    )
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
def _least_over_chunks(claims, parts, starts, out):
    for v in claimed_items(claims, out.shape[0], parts):
        for u in range(out.shape[1]):
            least = starts[0, v, u]
            for c in range(1, starts.shape[0]):
                least = min(least, starts[c, v, u])
            out[v, u] = least


def _view_constants(volume: FastTsdfVolume, pose: np.ndarray, camera: Intrinsics) -> tuple:
    """(camera as float64 fx, fy, cx, cy; rotation; origin; volume origin; voxel size): the
    view's arguments of the raycast's loops."""
    return (
        np.array([camera.fx, camera.fy, camera.cx, camera.cy], dtype=np.float64),
        np.ascontiguousarray(pose[:3, :3], dtype=np.float64),
        np.ascontiguousarray(pose[:3, 3], dtype=np.float64),
        np.asarray(volume.origin, dtype=np.float64),
        float(volume.voxel_size),
    )


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
def _chunk_starts(chunks: int, height: int, width: int) -> np.ndarray:
    """near_starts' per-chunk images, kept from frame to frame (fresh ones cost page faults)."""
    return np.empty((chunks, height, width), dtype=np.float32)


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
    above float32's rounding of coordinates within ~100 m, far below a sample step).
    Measured on redkitchen (frame 30): 1.70 jumps per ray after the start against
    2.92 with the camera's distance to each box, which this replaced."""
    chunks = _chunk_starts(numba.get_num_threads(), camera.height, camera.width)
    view = _view_constants(volume, pose, camera)
    inverse = _inverse_directions_work(camera.height, camera.width)
    run_parallel(_inverse_directions, view[0], view[1], inverse)
    # A run of boxes along the line of sight projects to about one box's pixels, a run across
    # it to a long slanted one (~2x the pixels of its boxes': measured on redkitchen).
    rotation = view[1]
    along_sight = abs(rotation[2, 2]) >= max(abs(rotation[0, 2]), abs(rotation[1, 2]))
    longest = near.shape[0] if along_sight else 1
    run_parallel(_near_box_starts, near, *view, inverse, longest, chunks, parts=len(chunks))
    starts = np.empty((camera.height, camera.width), dtype=np.float64)
    run_parallel(_least_over_chunks, chunks, starts)
    return starts


# ----------------------------------------------------------------------------------------------
# Two rays at a time: a CPU core overlaps one ray's chain of dependent loads with the other's.


@cpu_jit_numpy_errors_called
def march_two_rays(
    tsdf_weight: Any,
    offsets: tuple,
    empty: Any,
    fine_distance: Any,
    origin: Any,
    a: tuple,
    b: tuple,
    volume_origin: Any,
    voxel_size: float,
    step: float,
    safe_a: float,
    safe_b: float,
) -> tuple:
    """march_ray of two rays (unit directions a and b, from safe_a and safe_b) in
    lockstep: each step of one is a chain of dependent loads and roundings, so the core
    works on the other's meanwhile. The same answers as marching them one after the
    other."""
    n = tsdf_weight.shape[0]
    ray_a = march_start(origin, a, volume_origin, voxel_size, n, step, safe_a)
    ray_b = march_start(origin, b, volume_origin, voxel_size, n, step, safe_b)
    m_a, previous_a, known_a, crossing_a, value_a = ray_a[0], np.nan, ray_a[0] == 0, np.nan, 0.0
    m_b, previous_b, known_b, crossing_b, value_b = ray_b[0], np.nan, ray_b[0] == 0, np.nan, 0.0
    while m_a >= 0 or m_b >= 0:
        if m_a >= 0:
            m_a, previous_a, known_a, crossing_a, value_a = march_step(
                tsdf_weight,
                offsets,
                empty,
                fine_distance,
                origin,
                a,
                volume_origin,
                voxel_size,
                step,
                ray_a,
                (m_a, previous_a, known_a),
            )
        if m_b >= 0:
            m_b, previous_b, known_b, crossing_b, value_b = march_step(
                tsdf_weight,
                offsets,
                empty,
                fine_distance,
                origin,
                b,
                volume_origin,
                voxel_size,
                step,
                ray_b,
                (m_b, previous_b, known_b),
            )
    # Both refinements after both marches: two independent chains of loads and divisions
    # that the core overlaps (refining inside the step left one ray's chain alone at the
    # end: ~4 % of the cpu raycast, measured).
    hit_a = surface_at(
        tsdf_weight,
        offsets,
        origin,
        a,
        (crossing_a, value_a),
        previous_a,
        step,
        volume_origin,
        voxel_size,
    )
    hit_b = surface_at(
        tsdf_weight,
        offsets,
        origin,
        b,
        (crossing_b, value_b),
        previous_b,
        step,
        volume_origin,
        voxel_size,
    )
    return hit_a, hit_b


@cpu_jit_numpy_errors
def shade_two_pixels(
    tsdf_weight: Any,
    colour_volume: Any,
    has_colour: bool,
    offsets: tuple,
    pixels: tuple,
    hits: tuple,
    origin: Any,
    a: tuple,
    b: tuple,
    volume_origin: Any,
    voxel_size: float,
    vertices: Any,
    normals: Any,
    colours: Any,
) -> None:
    """shade_pixel of pixels (u_a, v) and (u_b, v), `pixels` = (u_a, u_b, v), whose rays
    (directions a and b) met the surface at `hits` = (t_a, t_b) (both finite), their normals
    taken together (gradient_normals)."""
    u_a, u_b, v = pixels
    o0, o1, o2 = offsets
    t_a, t_b = hits
    point_a = voxel_coordinates(origin, a, t_a, volume_origin, voxel_size)
    point_b = voxel_coordinates(origin, b, t_b, volume_origin, voxel_size)
    ax, ay, az = point_a
    bx, by, bz = point_b
    n = gradient_normals(tsdf_weight, o0, o1, o2, ax, ay, az, bx, by, bz)
    store_hit(
        colour_volume,
        has_colour,
        offsets,
        (u_a, v),
        t_a,
        origin,
        a,
        point_a,
        (n[0], n[1], n[2]),
        vertices,
        normals,
        colours,
    )
    store_hit(
        colour_volume,
        has_colour,
        offsets,
        (u_b, v),
        t_b,
        origin,
        b,
        point_b,
        (n[3], n[4], n[5]),
        vertices,
        normals,
        colours,
    )


@cpu_jit_numpy_errors
def raycast_pixel_pair(
    tsdf_weight: Any,
    colour_volume: Any,
    has_colour: bool,
    offsets: tuple,
    empty: Any,
    fine_distance: Any,
    pixel: tuple,
    march: tuple,
    camera: Any,
    rotation: Any,
    origin: Any,
    volume_origin: Any,
    vertices: Any,
    normals: Any,
    colours: Any,
    partner: tuple,
) -> None:
    """ops.raycast_pixel of `pixel` = (u, v) from its near_starts distance on, and with
    `partner` = (offset du > 0, its near_starts distance) of pixel (u + du, v) too: the two
    rays marched in lockstep (march_two_rays), then shaded together where both hit. `march` =
    (voxel size, step, the pixel's near_starts distance)."""
    u, v = pixel
    voxel_size, step, safe_until = march
    du, partner_safe_until = partner
    if du == 0:
        raycast_pixel(
            tsdf_weight,
            colour_volume,
            has_colour,
            offsets,
            empty,
            fine_distance,
            pixel,
            camera,
            rotation,
            origin,
            volume_origin,
            voxel_size,
            step,
            vertices,
            normals,
            colours,
            safe_until,
        )
        return
    a = ray_direction(u, v, camera, rotation)
    b = ray_direction(u + du, v, camera, rotation)
    t_a, t_b = march_two_rays(
        tsdf_weight,
        offsets,
        empty,
        fine_distance,
        origin,
        a,
        b,
        volume_origin,
        voxel_size,
        step,
        safe_until,
        partner_safe_until,
    )
    if math.isfinite(t_a) and math.isfinite(t_b):
        shade_two_pixels(
            tsdf_weight,
            colour_volume,
            has_colour,
            offsets,
            (u, u + du, v),
            (t_a, t_b),
            origin,
            a,
            b,
            volume_origin,
            voxel_size,
            vertices,
            normals,
            colours,
        )
        return
    for column, t, d in ((u, t_a, a), (u + du, t_b, b)):
        shade_pixel(
            tsdf_weight,
            colour_volume,
            has_colour,
            offsets,
            (column, v),
            t,
            origin,
            d,
            volume_origin,
            voxel_size,
            vertices,
            normals,
            colours,
        )


@parallel_part(error_model="numpy")
def _raycast_loop(
    claims,
    parts,
    tsdf_weight,
    colour_volume,
    has_colour,
    offsets,
    empty,
    fine_distance,
    camera,
    rotation,
    origin,
    volume_origin,
    voxel_size,
    step,
    vertices,
    normals,
    colours,
    stride,
    starts,
):
    # Every pixel cast is written once, hit or miss; with a stride, the thread that
    # casts a band first clears its rows (NaN, black) for the pixels left out (numpy's fill of
    # the three maps took ~2.5 ms on one thread, ~1.2 ms of a 2-thread raycast).
    height, width = vertices.shape[0], vertices.shape[1]
    span = BAND * stride
    for band in claimed_items(claims, -(-height // span), parts):
        rows = slice(band * span, min((band + 1) * span, height))
        if stride > 1:
            vertices[rows] = np.nan
            normals[rows] = np.nan
            colours[rows] = 0
        for v in range(band * span, min((band + 1) * span, height), stride):
            for u in range(0, width, 2 * stride):  # pixels two at a time
                du = stride if u + stride < width else 0
                raycast_pixel_pair(
                    tsdf_weight,
                    colour_volume,
                    has_colour,
                    offsets,
                    empty,
                    fine_distance,
                    (u, v),
                    (voxel_size, step, starts[v, u]),
                    camera,
                    rotation,
                    origin,
                    volume_origin,
                    vertices,
                    normals,
                    colours,
                    (du, starts[v, u + du]),
                )


def raycast(
    volume: FastTsdfVolume,
    pose: np.ndarray,
    camera: Intrinsics,
    skip_empty: bool = True,
    colour: bool = True,
    stride: int = 1,
) -> ModelPrediction:
    """Vertex, normal and colour maps of the model surface seen from `pose` (world frame);
    `skip_empty` (exact, as in the reference) jumps over bricks far from any surface; `colour`
    False leaves the colour map black; `stride` > 1 casts only the pixels whose u and v are
    multiples of it (kintinuous_ref.raycast.raycast)."""
    check_stride(stride)
    shape = (camera.height, camera.width)
    vertices = np.empty((*shape, 3), dtype=np.float32)  # _raycast_loop clears them
    normals = np.empty((*shape, 3), dtype=np.float32)
    colours = np.empty((*shape, 3), dtype=np.uint8)
    has_colour = colour and volume.colour is not None
    colour_volume = volume.colour if has_colour else np.zeros((1, 1, 1, 4), np.uint8)
    pose = np.asarray(pose, dtype=np.float64)
    if skip_empty:
        empty, fine_distance, near = _skip_maps_and_near(volume)
        starts = near_starts(volume, near, pose, camera)
    else:  # the plain march: maps of 0 skip nothing, every sample is taken
        empty = fine_distance = np.zeros((1, 1, 1), dtype=np.uint8)
        starts = np.zeros(shape, dtype=np.float64)
    # Rays cost very different amounts: a band of rows at a time, so that a thread that
    # finishes early, or was descheduled, evens out.
    run_parallel(
        _raycast_loop,
        volume.tsdf_weight,
        colour_volume,
        has_colour,
        volume.offsets(),
        empty,
        fine_distance,
        *_view_constants(volume, pose, camera),
        STEP_FRACTION * volume.truncation,
        vertices,
        normals,
        colours,
        int(stride),
        starts,
        parts=-(-camera.height // (BAND * int(stride))),
    )
    return ModelPrediction(pose=pose.copy(), vertices=vertices, normals=normals, colours=colours)
