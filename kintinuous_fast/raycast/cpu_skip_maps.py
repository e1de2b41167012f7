# ruff: noqa: ANN001, ANN201  (numba loops: argument types come from the call)
"""The cpu raycast's empty-space maps, from the per-fine-brick bit masks of observed negative
voxels that integration keeps up to date (negative_masks), so no frame scans the volume: the
brick map of kintinuous_ref.raycast.empty_space is the chessboard distance over the 8^3 bricks
holding a marked voxel, and the fine map (raycast.ops.FINE_DISTANCE_CAP) marks the fine bricks
holding the lower corner of a sample that may be negative.
"""

from __future__ import annotations

import functools
from types import SimpleNamespace

import numba
import numpy as np

from kintinuous_fast.raycast.ops import FINE_DISTANCE_CAP
from kintinuous_fast.targets import cpu_jit_numpy_errors
from kintinuous_fast.targets.cpu import claimed_items, parallel_part, run_parallel
from kintinuous_fast.tsdf import voxel
from kintinuous_fast.tsdf.volume import FastTsdfVolume, NegativeMasks
from kintinuous_fast.tsdf.voxel import BRICK, FINE

negative_mask = voxel.build_ops(cpu_jit_numpy_errors).negative_mask

# Bits of a fine brick's mask (tsdf.voxel.fine_voxel_bit: 4 a + 2 b + c for voxel (a, b, c)
# of the brick) at c = 0, and at b = c = 0.
_AT_C0, _AT_B0_C0 = np.uint8(0b01010101), np.uint8(0b00010001)


# The maps of _brick_maps from the fine masks (M, M, M): near[f] = any marked voxel among
# voxels 2f .. 2f + 2 on every axis, the corners of the samples whose lower corner lies in fine
# brick f, and negative[b] = any marked voxel in 8^3 brick b (kintinuous_ref.raycast.
# empty_space's). near comes from three separable passes: along k then j, a brick's voxels and
# the next brick's first fold into its bits at c = 0 (`rows`), then at b = c = 0 (`planes`);
# along i, the same decides `near`. Bytes are combined with | and &, so the loops have no
# branches and vectorise; each pass writes a fresh array, as folding in place keeps LLVM from
# vectorising them.


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
    """The skip maps' work arrays for one volume size, kept from frame to frame: fresh ones cost
    page faults every frame (docs/benchmarks.md, "Numbers behind the fast stages")."""
    fine_shape, shape = (fine_bricks,) * 3, (bricks,) * 3
    return SimpleNamespace(
        rows=np.empty(fine_shape, dtype=np.uint8),
        planes=np.empty(fine_shape, dtype=np.uint8),
        near=np.empty(fine_shape, dtype=np.bool_),
        negative=np.empty(shape, dtype=np.bool_),
    )


def _brick_maps(volume: FastTsdfVolume) -> tuple[np.ndarray, SimpleNamespace]:
    """(empty, work): kintinuous_ref.raycast.empty_space of the volume (int64 brick distances)
    and the work arrays, whose `near` map of fine bricks (bool) skip_maps turns into distances,
    both from the negative-voxel masks."""
    masks = negative_masks(volume)
    work = _work_arrays(masks.shape[0], -(-volume.resolution // BRICK))
    run_parallel(_fold_rows_and_planes, masks, work.rows, work.planes)
    run_parallel(_fold_slabs, work.planes, work.near)
    run_parallel(_negative_bricks, masks, work.negative)
    return _brick_distance(work.negative), work


def _brick_distance(negative: np.ndarray) -> np.ndarray:
    """kintinuous_ref.raycast.empty_space from its (B, B, B) map of bricks holding an observed
    negative voxel (int64). Growing by one brick and then taking the chessboard distance is the
    chessboard distance less one, floored at 0; _capped_distance gives it with a cap (B + 1)
    that no distance inside the grid reaches (in numba: scipy's dilation and transform cost
    an order of magnitude more, docs/benchmarks.md, "Numbers behind the fast stages")."""
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
# (axis 0). The passes may lower a pad; no entry reads one after the first pass. Shifting whole
# planes, not each row of 128 on its own, keeps the loops long (docs/benchmarks.md, "Numbers
# behind the fast stages").


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
    """target = source, elementwise over 1-d arrays (numba's slice assignment is several times
    slower on rows of 128)."""
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
    return skip_maps_and_near(volume)[:2]


def skip_maps_and_near(volume: FastTsdfVolume) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """skip_maps and the `near` map of fine bricks they come from (work arrays)."""
    empty, work = _brick_maps(volume)
    fine_distance = _capped_distance(work.near, FINE_DISTANCE_CAP)
    # uint8: the map stays in the first-level cache; a smaller distance only means shorter jumps
    return np.minimum(empty, 255).astype(np.uint8), fine_distance, work.near


def empty_space(volume: FastTsdfVolume) -> np.ndarray:
    """kintinuous_ref.raycast.empty_space of the fast volume (brick distance map, int64)."""
    return _brick_maps(volume)[0]


@parallel_part(error_model="numpy")
def _mask_loop(claims, parts, tsdf_weight, o0, o1, o2, masks):
    m = masks.shape[0]
    for f0 in claimed_items(claims, m, parts):
        for f1 in range(m):
            for f2 in range(m):
                masks[f0, f1, f2] = negative_mask(tsdf_weight, o0, o1, o2, f0, f1, f2)


def negative_masks(volume: FastTsdfVolume) -> np.ndarray:
    """Per logical fine brick of FINE^3 voxels, the bit mask of its observed negative voxels
    (tsdf.voxel.fine_voxel_bit), (M, M, M) uint8: those integration kept up to date, or taken
    from the volume now (after a shift, or clearing) and kept for the following frames."""
    masks = volume.current_negative_masks()
    if masks is None:
        m = -(-volume.resolution // FINE)
        masks = np.empty((m, m, m), dtype=np.uint8)
        run_parallel(_mask_loop, volume.tsdf_weight, *volume.offsets(), masks)
        volume.negative_masks = NegativeMasks(masks, volume.offsets())
    return masks
