# ruff: noqa: ANN001, ANN201  (numba kernels and loops: argument types come from the call)
"""kintinuous_ref.raycast on the CPU: a loop over bands of pixel rows (on all threads) around
kintinuous_fast.raycast.ops, with the reference's exact brick empty-space skipping plus a finer
second level inside the bricks next to a surface (raycast.cpu_skip_maps). Each ray starts where
it first enters a fine brick that may hold a negative sample (raycast.cpu_near_starts), and
rays go on from there two at a time, in lockstep (march_two_rays below). Every skip is exact:
the maps are the plain march's.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from kintinuous_fast.raycast.cpu_near_starts import near_starts
from kintinuous_fast.raycast.cpu_ops import OPS, VOXELS
from kintinuous_fast.raycast.cpu_skip_maps import empty_space, skip_maps_and_near
from kintinuous_fast.targets import cpu_jit_numpy_errors, cpu_jit_numpy_errors_called
from kintinuous_fast.targets.cache import register_slowest
from kintinuous_fast.targets.cpu import claimed_items, parallel_part, run_parallel, threads
from kintinuous_fast.tsdf.volume import FastTsdfVolume, view_constants
from kintinuous_ref.camera import Intrinsics
from kintinuous_ref.raycast import STEP_FRACTION, ModelPrediction, check_stride

__all__ = [
    "STEP_FRACTION",
    "ModelPrediction",
    "check_stride",
    "empty_space",
    "predict_surface",
    "raycast",
]

# The shared per-ray functions this file builds on, as globals numba can call.
march_start, march_step, surface_at = OPS.march_start, OPS.march_step, OPS.surface_at
raycast_pixel, ray_direction, shade_pixel = OPS.raycast_pixel, OPS.ray_direction, OPS.shade_pixel
voxel_coordinates, store_hit = OPS.voxel_coordinates, OPS.store_hit
gradient_normals = VOXELS.gradient_normals
# The least rows of the image's last bands (_band_starts).
MIN_BAND = 2


def _band_starts(rows: int, threads: int) -> np.ndarray:
    """The first of the `rows` cast rows of each band the raycast's threads claim in order, and
    `rows` last: each band a 2 * threads-th of the rows not yet handed out, at least MIN_BAND
    (guided scheduling). Rays cost very different amounts; large bands first keep a thread's
    rays near each other in the volume, small ones last leave a thread that finishes early
    little to wait for (on two threads, fixed bands of 8 rows kept one thread waiting 0.7-1.0
    ms of a 45 ms call, these 0.15-0.3 ms: benchmarks/loop_anatomy.py)."""
    starts = [0]
    while starts[-1] < rows:
        left = rows - starts[-1]
        starts.append(starts[-1] + min(left, max(MIN_BAND, left // (2 * threads))))
    return np.array(starts, dtype=np.int64)


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
    # that the core overlaps (refining inside the step would leave one ray's chain alone at
    # the end).
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


@register_slowest("raycast")
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
    bands,
):
    # Every pixel cast is written once, hit or miss; with a stride, the thread that
    # casts a band first clears its rows (NaN, black) for the pixels left out, so that no
    # single-threaded fill of the three maps comes first.
    height, width = vertices.shape[0], vertices.shape[1]
    for band in claimed_items(claims, bands.shape[0] - 1, parts):
        first, end = bands[band] * stride, min(bands[band + 1] * stride, height)
        if stride > 1:
            vertices[first:end] = np.nan
            normals[first:end] = np.nan
            colours[first:end] = 0
        for v in range(first, end, stride):
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
        empty, fine_distance, near = skip_maps_and_near(volume)
        starts = near_starts(volume, near, pose, camera)
    else:  # the plain march: maps of 0 skip nothing, every sample is taken
        empty = fine_distance = np.zeros((1, 1, 1), dtype=np.uint8)
        starts = np.zeros(shape, dtype=np.float64)
    bands = _band_starts(-(-camera.height // int(stride)), threads())
    run_parallel(
        _raycast_loop,
        volume.tsdf_weight,
        colour_volume,
        has_colour,
        volume.offsets(),
        empty,
        fine_distance,
        *view_constants(volume, pose, camera),
        STEP_FRACTION * volume.truncation,
        vertices,
        normals,
        colours,
        int(stride),
        starts,
        bands,
        parts=len(bands) - 1,
    )
    return ModelPrediction(pose=pose.copy(), vertices=vertices, normals=normals, colours=colours)


def predict_surface(
    volume: FastTsdfVolume, pose: np.ndarray, camera: Intrinsics, stride: int = 1
) -> ModelPrediction:
    """The model prediction the next frame tracks against: vertices and normals, no colour
    (kintinuous_ref.raycast.predict_surface)."""
    return raycast(volume, pose, camera, colour=False, stride=stride)
