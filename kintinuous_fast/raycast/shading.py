"""The per-pixel part of the raycast, written once for the CPU and the CUDA target: a pixel's
ray marched (raycast.ops) and, where it meets the surface, its vertex, TSDF-gradient normal and
colour written to the maps (kintinuous_ref.raycast.raycast).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from types import SimpleNamespace
from typing import Any

import numpy as np


def build_shading(
    jit: Callable[[Any], Any], voxels: SimpleNamespace, ray_ops: SimpleNamespace
) -> SimpleNamespace:
    """The maps' entries of a pixel whose ray met the surface, or did not."""
    gradient_normal, surface_colour_at = voxels.gradient_normal, voxels.surface_colour_at
    voxel_coordinates = ray_ops.voxel_coordinates

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

    return SimpleNamespace(shade_pixel=shade_pixel, store_hit=store_hit, store_miss=store_miss)


def build_pixel(
    jit: Callable[[Any], Any],
    ray_ops: SimpleNamespace,
    march_ops: SimpleNamespace,
    shading_ops: SimpleNamespace,
) -> SimpleNamespace:
    """One pixel of the raycast: its ray marched, then shaded."""
    ray_direction, march_ray = ray_ops.ray_direction, march_ops.march_ray
    shade_pixel = shading_ops.shade_pixel

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

    return SimpleNamespace(raycast_pixel=raycast_pixel)
