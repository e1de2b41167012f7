# ruff: noqa: ANN001, ANN201  (numba loops: argument types come from the call)
"""Which voxels of a column cpu integration visits: per bundle of columns, the range along k of
the bricks where some voxel may be updated this frame, from a max pyramid of the measured
distances (a brick wholly behind the surface, or outside the image, is left out).
"""

from __future__ import annotations

import math

import numba
import numpy as np

from kintinuous_fast.targets.cpu import claimed_items, parallel_part, run_parallel
from kintinuous_fast.tsdf.volume import (
    FastTsdfVolume,
    image_size,
    index_box,
    projection_constants,
)
from kintinuous_ref.camera import Intrinsics

# Integration leaves out the voxels of a column that lie in bricks of CULL_BRICK voxels where
# no voxel can be updated: every pixel the brick can project to measures a distance lambda D
# short of the brick's nearest point by more than mu (all behind the surface), or has no
# depth. Most of a frame's projected voxels lie behind the surface, and these bricks hold about
# half of them (docs/benchmarks.md, "Numbers behind the fast stages"). CULL_MARGIN (metres) dwarfs
# float32's rounding of voxel positions and distances (~1e-6 m), so no voxel that the exact test
# updates is left out.
CULL_BRICK = (8, 8, 16)
CULL_MARGIN = 1e-4
DEPTH_TILE = 8  # pixels per side of the finest level of the max pyramid of lambda D


@parallel_part(error_model="numpy")
def _tile_maxima(claims, parts, ray_distance, height, width, out):
    """out[tv, tu] = the largest lambda D over tile (tv, tu) of DEPTH_TILE^2 pixels (-inf: no
    depth there), from the flat ray distances of _ray_distance_loop."""
    for tv in claimed_items(claims, out.shape[0], parts):
        for tu in range(out.shape[1]):
            largest = np.float32(-np.inf)
            for v in range(tv * DEPTH_TILE, min((tv + 1) * DEPTH_TILE, height)):
                for u in range(tu * DEPTH_TILE, min((tu + 1) * DEPTH_TILE, width)):
                    largest = max(largest, ray_distance[v * width + u])
            out[tv, tu] = largest


def _max_pyramid(ray_distance: np.ndarray, height: int, width: int) -> np.ndarray:
    """(L, H0, W0) float32: level l holds the largest lambda D over tiles of DEPTH_TILE 2^l
    pixels per side, -inf where no pixel has depth or beyond the level's tiles; the last
    level is a single tile."""
    finest = np.empty((-(-height // DEPTH_TILE), -(-width // DEPTH_TILE)), dtype=np.float32)
    run_parallel(_tile_maxima, ray_distance, height, width, finest)
    levels = [finest]
    while levels[-1].shape != (1, 1):
        last = levels[-1]
        rows, cols = -(-last.shape[0] // 2), -(-last.shape[1] // 2)
        padded = np.full((2 * rows, 2 * cols), -np.inf, dtype=np.float32)
        padded[: last.shape[0], : last.shape[1]] = last
        levels.append(padded.reshape(rows, 2, cols, 2).max(axis=(1, 3)))
    pyramid = np.full((len(levels), *finest.shape), -np.inf, dtype=np.float32)
    for level, maxima in enumerate(levels):
        pyramid[level, : maxima.shape[0], : maxima.shape[1]] = maxima
    return pyramid


@numba.njit(cache=True, error_model="numpy", inline="always")
def _largest_over(pyramid, u0, u1, v0, v1):
    """An upper bound of lambda D over pixels [u0, u1] x [v0, v1]: the largest of the (at most
    2 x 2) tiles covering them at the finest level where they span no more."""
    for level in range(pyramid.shape[0]):
        size = DEPTH_TILE << level
        a0, a1, b0, b1 = u0 // size, u1 // size, v0 // size, v1 // size
        if a1 - a0 <= 1 and b1 - b0 <= 1:
            largest = np.float32(-np.inf)
            for b in range(b0, b1 + 1):
                for a in range(a0, a1 + 1):
                    largest = max(largest, pyramid[level, b, a])
            return largest
    return pyramid[pyramid.shape[0] - 1, 0, 0]


@parallel_part(error_model="numpy")
def _columns_to_visit_loop(
    claims, parts, base, steps, camera_voxel, intrinsics, image_size, pyramid, box, cull, visit
):
    """visit[I, J] = [k0, k1): the voxels along k, within the box [lo, hi) = `box`, that the
    columns of CULL_BRICK[0] x CULL_BRICK[1] bundle (I, J) visit: from the first of its bricks of
    CULL_BRICK voxels that may hold a voxel this frame updates (_brick_may_update) to the
    last (k0 = k1 when none may). A range, not a brick map: a brick lookup inside the
    column loop keeps LLVM from compiling that loop as well."""
    sizes = CULL_BRICK
    lo, hi = box
    for b0 in claimed_items(claims, visit.shape[0], parts):
        i0, i1 = max(b0 * sizes[0], lo[0]), min((b0 + 1) * sizes[0], hi[0]) - 1
        for b1 in range(visit.shape[1]):
            j0, j1 = max(b1 * sizes[1], lo[1]), min((b1 + 1) * sizes[1], hi[1]) - 1
            first, end = hi[2], hi[2]
            for b2 in range(-(-hi[2] // sizes[2])):
                k0, k1 = max(b2 * sizes[2], lo[2]), min((b2 + 1) * sizes[2], hi[2]) - 1
                if (
                    i0 <= i1
                    and j0 <= j1
                    and k0 <= k1
                    and _brick_may_update(
                        base,
                        steps,
                        camera_voxel,
                        intrinsics,
                        image_size,
                        pyramid,
                        cull,
                        (i0, j0, k0),
                        (i1, j1, k1),
                    )
                ):
                    first = min(first, k0)
                    end = k1 + 1
            visit[b0, b1, 0], visit[b0, b1, 1] = first, max(end, first)


@numba.njit(cache=True, error_model="numpy", inline="always")
def _brick_may_update(
    base, steps, camera_voxel, intrinsics, image_size, pyramid, cull, first, last
):
    """Whether a voxel of [i0, i1] x [j0, j1] x [k0, k1] (`first` = (i0, j0, k0), `last` =
    (i1, j1, k1)) may be updated: unless its corners all lie in front of the camera and the
    largest lambda D over the pixels of its projection's bounds (grown by a pixel: voxels round
    to the nearest) plus `reach` falls short of its nearest point's distance (the camera at
    `camera_voxel` in voxel coordinates, clamped into the block: the voxel grid is a scaled
    rotation of the camera frame), or it projects wholly outside the image. `cull` = (reach,
    voxel size), `image_size` = (W, H)."""
    i0, j0, k0 = first
    i1, j1, k1 = last
    width, height = image_size
    reach, voxel_size = cull
    u_lo, u_hi, v_lo, v_hi = np.inf, -np.inf, np.inf, -np.inf
    for i in (i0, i1):
        for j in (j0, j1):
            for k in (k0, k1):
                x = base[0] + i * steps[0, 0] + j * steps[1, 0] + k * steps[2, 0]
                y = base[1] + i * steps[0, 1] + j * steps[1, 1] + k * steps[2, 1]
                z = base[2] + i * steps[0, 2] + j * steps[1, 2] + k * steps[2, 2]
                if not z > 1e-6:
                    return True  # reaches behind the camera's plane: no bounds to go by
                u = intrinsics[0] * x / z + intrinsics[2]
                v = intrinsics[1] * y / z + intrinsics[3]
                u_lo, u_hi = min(u_lo, u), max(u_hi, u)
                v_lo, v_hi = min(v_lo, v), max(v_hi, v)
    u0 = max(int(math.floor(u_lo)) - 1, 0)
    u1 = min(int(math.ceil(u_hi)) + 1, width - 1)
    v0 = max(int(math.floor(v_lo)) - 1, 0)
    v1 = min(int(math.ceil(v_hi)) + 1, height - 1)
    if u0 > u1 or v0 > v1:
        return False  # wholly outside the image
    dx = min(max(camera_voxel[0], i0), i1) - camera_voxel[0]
    dy = min(max(camera_voxel[1], j0), j1) - camera_voxel[1]
    dz = min(max(camera_voxel[2], k0), k1) - camera_voxel[2]
    nearest = voxel_size * math.sqrt(dx * dx + dy * dy + dz * dz)
    return nearest <= float(_largest_over(pyramid, u0, u1, v0, v1)) + reach


def columns_to_visit(
    volume: FastTsdfVolume,
    box: tuple[np.ndarray, np.ndarray],
    base: np.ndarray,
    steps: np.ndarray,
    camera: Intrinsics,
    ray_distance: np.ndarray,
    pose: np.ndarray,
) -> np.ndarray:
    """Per bundle of CULL_BRICK[0] x CULL_BRICK[1] columns, the range of k they visit (int64,
    _columns_to_visit_loop)."""
    n = volume.resolution
    visit = np.empty((-(-n // CULL_BRICK[0]), -(-n // CULL_BRICK[1]), 2), dtype=np.int64)
    camera_voxel = volume.world_to_voxel(pose[:3, 3][None])[0].astype(np.float64)
    lo, hi = index_box(box)
    reach = float(volume.truncation) + CULL_MARGIN
    run_parallel(
        _columns_to_visit_loop,
        base,
        steps,
        camera_voxel,
        projection_constants(camera),
        image_size(camera),
        _max_pyramid(ray_distance, camera.height, camera.width),
        (lo, hi),
        (reach, float(volume.voxel_size)),
        visit,
    )
    return visit
