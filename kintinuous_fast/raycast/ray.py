"""One ray's geometry, written once for the CPU and the CUDA target: its direction and span in
the volume, the voxel coordinates of its samples, and the arithmetic of the empty-space jumps
(where a ray leaves a cube of bricks). Small scalar helpers: the cpu raycast compiles them as
calls that LLVM inlines (raycast.ops.build_ops' `jit_called`).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from types import SimpleNamespace
from typing import Any

import numpy as np

from kintinuous_fast.tsdf.voxel import FINE

# Voxels by which the cpu raycast's jumps shrink an empty cube: far above the rounding of sample
# coordinates (~1e-13 voxels), far below a sample step (~2 voxels).
JUMP_MARGIN = 1e-6


def build_ray(jit_called: Callable[[Any], Any]) -> SimpleNamespace:
    """A ray's direction, span, sample coordinates and the secant of a crossing."""

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
        inverse where the reference divides (within an ulp: a ray's samples move by ~1e-16 m),
        which keeps three divisions per ray out of the cpu raycast."""
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

    @jit_called
    def inverse_or_zero(x: float) -> float:
        return 1.0 / x if x != 0 else 0.0

    @jit_called
    def voxel_coordinates(
        origin: Any, direction: tuple, t: float, volume_origin: Any, voxel_size: float
    ) -> tuple:
        """Continuous voxel coordinates of the ray point at t (sample_along's). The reference
        divides by the voxel size; a multiply by its inverse (within an ulp of the quotient)
        keeps the division's latency out of every sample."""
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

    return SimpleNamespace(
        axis_interval=axis_interval,
        inverse_or_zero=inverse_or_zero,
        ray_direction=ray_direction,
        ray_span=ray_span,
        voxel_coordinates=voxel_coordinates,
        zero_crossing=zero_crossing,
    )


def build_jumps(jit_called: Callable[[Any], Any]) -> SimpleNamespace:
    """Where a ray's samples leave an empty cube of bricks or fine bricks (march_step's jumps)."""

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
    def whole_fine(c: float) -> int:
        """floor(c / FINE): the fine brick of coordinate c, unclamped."""
        return math.floor(c * (1.0 / FINE))

    @jit_called
    def clear_of_faces(c: float, whole: int) -> bool:
        """Whether coordinate c (whole = whole_fine(c)) is more than JUMP_MARGIN voxels from
        every fine brick face."""
        f = c * (1.0 / FINE) - whole
        return f >= JUMP_MARGIN / FINE and f <= 1.0 - JUMP_MARGIN / FINE

    return SimpleNamespace(
        clear_of_faces=clear_of_faces,
        fine_index=fine_index,
        first_sample_outside=first_sample_outside,
        samples_to_leave=samples_to_leave,
        whole_fine=whole_fine,
    )
