# ruff: noqa: ANN001, ANN201  (numba kernels and loops: argument types come from the call)
"""kintinuous_ref.raycast on the CPU: one ray per pixel in a prange loop around
kintinuous_fast.ops.volume, with the reference's exact brick empty-space skipping plus a finer
second level inside the bricks next to a surface.

Both levels come from the per-fine-brick counts of observed negative voxels that integration
keeps up to date (kintinuous_fast.cpu.tsdf.negative_counts), so no frame scans the volume: the
brick map of kintinuous_ref.raycast._empty_space is the chessboard distance over the 8^3 bricks
holding a counted voxel, and the fine map marks the fine bricks whose samples may be negative.
"""

from __future__ import annotations

import numba
import numpy as np
from numba import prange

from kintinuous_fast._volume import FastTsdfVolume, empty_space_distance
from kintinuous_fast.cpu.tsdf import negative_counts
from kintinuous_fast.ops import cpu_jit_numpy_errors
from kintinuous_fast.ops.volume import BRICK, FINE, build_ops
from kintinuous_ref.camera import Intrinsics
from kintinuous_ref.raycast import STEP_FRACTION, ModelPrediction

__all__ = ["STEP_FRACTION", "ModelPrediction", "empty_space", "raycast"]

_ops = build_ops(cpu_jit_numpy_errors)
raycast_pixel = _ops.raycast_pixel
ROWS_PER_CHUNK = 4  # rows handed to a thread at a time (dynamic scheduling of the rays)


@numba.njit(parallel=True, cache=True, error_model="numpy")
def _brick_maps(counts, pairs, near, negative):
    """From the fine counts (M, M, M): near[f] = any count in f .. f + 1 along each axis (three
    separable passes of "this or the next": along k and j into `pairs`, along i into `near`),
    and negative[b] = any count in 8^3 brick b (kintinuous_ref.raycast._empty_space's)."""
    m = counts.shape[0]
    per_brick = BRICK // FINE
    for f0 in prange(m):
        for f1 in range(m):
            for f2 in range(m - 1):
                pairs[f0, f1, f2] = counts[f0, f1, f2] > 0 or counts[f0, f1, f2 + 1] > 0
            pairs[f0, f1, m - 1] = counts[f0, f1, m - 1] > 0
        for f1 in range(m - 1):
            for f2 in range(m):
                pairs[f0, f1, f2] = pairs[f0, f1, f2] or pairs[f0, f1 + 1, f2]
    for f0 in prange(m):
        last = f0 == m - 1
        for f1 in range(m):
            for f2 in range(m):
                near[f0, f1, f2] = pairs[f0, f1, f2] or (not last and pairs[f0 + 1, f1, f2])
    for b0 in prange(negative.shape[0]):  # each thread writes its own slab of bricks
        for f0 in range(b0 * per_brick, min((b0 + 1) * per_brick, m)):
            for f1 in range(m):
                for f2 in range(m):
                    if counts[f0, f1, f2] > 0:
                        negative[b0, f1 // per_brick, f2 // per_brick] = True


def brick_maps(volume: FastTsdfVolume) -> tuple[np.ndarray, np.ndarray]:
    """(empty, near): kintinuous_ref.raycast._empty_space of the volume (int64 brick distances)
    and the fine map of march_ray (bool per fine brick), from the negative-voxel counts."""
    counts = negative_counts(volume)
    m = counts.shape[0]
    near = np.empty((m, m, m), dtype=np.bool_)
    b = -(-volume.resolution // BRICK)
    negative = np.zeros((b, b, b), dtype=np.bool_)
    _brick_maps(counts, np.empty_like(near), near, negative)
    return empty_space_distance(negative), near


def empty_space(volume: FastTsdfVolume) -> np.ndarray:
    """kintinuous_ref.raycast._empty_space of the fast volume (brick distance map, int64)."""
    return brick_maps(volume)[0]


@numba.njit(parallel=True, cache=True, error_model="numpy")
def _raycast_loop(
    tsdf_weight,
    colour_volume,
    has_colour,
    o0,
    o1,
    o2,
    empty,
    near,
    camera,
    rotation,
    origin,
    volume_origin,
    voxel_size,
    step,
    vertices,
    normals,
    colours,
):
    # rays cost very different amounts: rows are handed out a few at a time (the caller sets
    # the chunk size), so a thread that finishes early, or was descheduled, evens out
    for v in prange(vertices.shape[0]):
        for u in range(vertices.shape[1]):
            raycast_pixel(
                tsdf_weight, colour_volume, has_colour, o0, o1, o2, empty, near, u, v, camera,
                rotation, origin, volume_origin, voxel_size, step, vertices, normals, colours,
            )  # fmt: skip


def raycast(
    volume: FastTsdfVolume, pose: np.ndarray, camera: Intrinsics, skip_empty: bool = True
) -> ModelPrediction:
    """Vertex, normal and colour maps of the model surface seen from `pose` (world frame);
    `skip_empty` (exact, as in the reference) jumps over bricks far from any surface."""
    shape = (camera.height, camera.width)
    vertices = np.full((*shape, 3), np.nan, dtype=np.float32)
    normals = np.full((*shape, 3), np.nan, dtype=np.float32)
    colours = np.zeros((*shape, 3), dtype=np.uint8)
    has_colour = volume.colour is not None
    colour_volume = volume.colour if has_colour else np.zeros((1, 1, 1, 4), np.uint8)
    pose = np.asarray(pose, dtype=np.float64)
    if skip_empty:
        empty, near = brick_maps(volume)
    else:  # the plain march: every sample taken
        empty, near = np.zeros((1, 1, 1), dtype=np.int64), np.ones((1, 1, 1), dtype=np.bool_)
    with numba.parallel_chunksize(ROWS_PER_CHUNK):
        _raycast_loop(
            volume.tsdf_weight,
            colour_volume,
            has_colour,
            *volume.offsets(),
            empty,
            near,
            np.array([camera.fx, camera.fy, camera.cx, camera.cy], dtype=np.float64),
            np.ascontiguousarray(pose[:3, :3]),
            np.ascontiguousarray(pose[:3, 3]),
            np.asarray(volume.origin, dtype=np.float64),
            float(volume.voxel_size),
            STEP_FRACTION * volume.truncation,
            vertices,
            normals,
            colours,
        )
    return ModelPrediction(pose=pose.copy(), vertices=vertices, normals=normals, colours=colours)
