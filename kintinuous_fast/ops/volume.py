"""The stored voxels, written once for the CPU and the CUDA target: quantisation, the cyclical
buffer's cells, and sampling (trilinear TSDF, its gradient, surface colour) that the raycast and
the moving volume share. Integration (ops.integration) and the march (ops.march) build on them.

The fast volume stores what the GPU design of Kintinuous stores, 8 bytes per voxel (1 GiB at
512^3): `tsdf_weight` (N, N, N, 2) int16 holds round(F * 32767) and the integer weight W (the
reference's weights are integers too: +1 per frame, capped), and `colour` (N, N, N, 4) uint8 holds
R, G, B and the colour weight rounded to an integer (at least 1 once any colour arrived). The
reference keeps float32 for all of them; the arithmetic below is the reference's, in the same
precision and order, with a rounding to the stored type at the end of each update.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from types import SimpleNamespace
from typing import Any

import numpy as np

TSDF_SCALE = 32767.0  # int16 units per unit of normalised TSDF
TSDF_MAX = 32767  # the stored F = 1
TSDF_INVERSE_SCALE = 1.0 / TSDF_SCALE
BRICK = 8  # voxels per side of the empty-space bricks (kintinuous_ref.raycast.BRICK)
# Voxels per side of the fine bricks whose observed negative voxels integration counts (the cpu
# raycast's second level of empty-space skipping, inside the bricks next to a surface).
FINE = 2

# Cyclical buffer (kintinuous_ref.tsdf, moving volume): logical voxel l lives in array cell
# (l + offset) mod N, offset in [0, N). Every function below takes the offset as three ints
# (o0, o1, o2) and maps logical indices with `cell` (one compare, no division).


def build_ops(
    jit: Callable[[Any], Any],
    jit_called: Callable[[Any], Any] | None = None,
    dequantise_table: bool = False,
) -> SimpleNamespace:
    """The voxel functions compiled with `jit`; the two large per-ray ones (a normal, a colour)
    with `jit_called` (default `jit`). The cpu backend's `jit` inlines at numba IR level, which
    is what makes the per-voxel loops fast, but inlining a whole march and its samples into
    every caller made the raycast take minutes to compile; called once per ray, these lose
    nothing by being calls. With `dequantise_table`, dequantise reads its (equal) values from a
    table of all 65536 (256 KiB): a load instead of three conversions and a multiply made the
    cpu raycast ~4 % faster (its samples and normals dequantise ~80 values per ray), but cpu
    integration, one value per updated voxel, ~4 % slower: it keeps the arithmetic, and so
    does CUDA, whose constant memory holds 64 KiB."""
    jit_called = jit_called or jit

    if dequantise_table:
        # the same products as below, for every int16; numba freezes the closure's table into
        # the compiled code as a constant
        table = (np.arange(-32768, 32768) * TSDF_INVERSE_SCALE).astype(np.float32)

        @jit
        def dequantise(q: Any) -> Any:
            """The arithmetic dequantise's value, read from the table of every int16."""
            return table[np.intp(q) + 32768]

    else:

        @jit
        def dequantise(q: Any) -> Any:
            """float32 TSDF of a stored int16: q / 32767 correctly rounded to float32, the
            division to_reference_volume does. Computed as a float64 product (a float32
            division costs ~4x a multiply, and the raycast's normals take 48 of them): its
            error (~1e-16 relative) is far below the gap between q / 32767 and any float32
            rounding midpoint (> 2^-39 relative, as 32767 is odd), so it rounds the same way;
            checked for every int16 by the tests."""
            return np.float32(float(q) * TSDF_INVERSE_SCALE)

    @jit
    def quantise(f: Any) -> int:
        """Nearest int16 of F * 32767, F in [-1, 1]."""
        q = round(float(f) * TSDF_SCALE)
        return min(max(q, -32767), 32767)

    @jit
    def cell(index: int, offset: int, n: int) -> int:
        """Array cell of logical index `index` in [0, N) with buffer offset in [0, N), unsigned:
        numba then indexes without its negative-index wraparound (a compare and select per
        index, which also keeps LLVM from vectorising)."""
        c = index + offset
        return np.uint64(c - n if c >= n else c)

    @jit
    def sample_tsdf_at(
        tsdf_weight: Any, o0: int, o1: int, o2: int, cx: float, cy: float, cz: float
    ) -> float:
        """Trilinear TSDF over the OBSERVED corners only (weights renormalised), float64;
        NaN outside [0, N-1]^3 or when no corner is observed (kintinuous_ref.tsdf.sample_tsdf).
        (cx, cy, cz) are logical voxel coordinates."""
        n = tsdf_weight.shape[0]
        if not (cx >= 0 and cx <= n - 1 and cy >= 0 and cy <= n - 1 and cz >= 0 and cz <= n - 1):
            return np.nan
        bx = min(max(int(math.floor(cx)), 0), n - 2)
        by = min(max(int(math.floor(cy)), 0), n - 2)
        bz = min(max(int(math.floor(cz)), 0), n - 2)
        fx = min(max(cx - bx, 0.0), 1.0)
        fy = min(max(cy - by, 0.0), 1.0)
        fz = min(max(cz - bz, 0.0), 1.0)
        total = 0.0
        coverage = 0.0
        for a in range(2):
            wa = fx if a else 1.0 - fx
            ia = cell(bx + a, o0, n)
            for b in range(2):
                wb = fy if b else 1.0 - fy
                ib = cell(by + b, o1, n)
                for c in range(2):
                    wc = fz if c else 1.0 - fz
                    ic = cell(bz + c, o2, n)
                    if tsdf_weight[ia, ib, ic, 1] > 0:
                        w = wa * wb * wc
                        total += w * float(dequantise(tsdf_weight[ia, ib, ic, 0]))
                        coverage += w
        if not coverage > 1e-6:
            return np.nan
        return total / coverage

    @jit
    def trilinear_tsdf(
        tsdf_weight: Any, o0: int, o1: int, o2: int, cx: float, cy: float, cz: float
    ) -> Any:
        """Plain trilinear TSDF (unobserved voxels count as 0), float32 like tsdf.trilinear."""
        n = tsdf_weight.shape[0]
        bx = min(max(int(math.floor(cx)), 0), n - 2)
        by = min(max(int(math.floor(cy)), 0), n - 2)
        bz = min(max(int(math.floor(cz)), 0), n - 2)
        fx = min(max(cx - bx, 0.0), 1.0)
        fy = min(max(cy - by, 0.0), 1.0)
        fz = min(max(cz - bz, 0.0), 1.0)
        total = 0.0
        for a in range(2):
            wa = fx if a else 1.0 - fx
            ia = cell(bx + a, o0, n)
            for b in range(2):
                wb = fy if b else 1.0 - fy
                ib = cell(by + b, o1, n)
                for c in range(2):
                    wc = fz if c else 1.0 - fz
                    value = float(dequantise(tsdf_weight[ia, ib, cell(bz + c, o2, n), 0]))
                    total += wa * wb * wc * value
        return np.float32(total)

    @jit
    def clip(c: float, limit: float) -> float:
        return min(max(c, 0.0), limit)

    @jit_called
    def gradient_normal(
        tsdf_weight: Any, o0: int, o1: int, o2: int, cx: float, cy: float, cz: float
    ) -> tuple:
        """Unit TSDF gradient by central differences one voxel apart (raycast._gradient_normals);
        NaN when it vanishes."""
        limit = tsdf_weight.shape[0] - 1.0
        px, py, pz = clip(cx, limit), clip(cy, limit), clip(cz, limit)
        t = tsdf_weight
        gx = trilinear_tsdf(t, o0, o1, o2, clip(cx + 1.0, limit), py, pz) - trilinear_tsdf(
            t, o0, o1, o2, clip(cx - 1.0, limit), py, pz
        )
        gy = trilinear_tsdf(t, o0, o1, o2, px, clip(cy + 1.0, limit), pz) - trilinear_tsdf(
            t, o0, o1, o2, px, clip(cy - 1.0, limit), pz
        )
        gz = trilinear_tsdf(t, o0, o1, o2, px, py, clip(cz + 1.0, limit)) - trilinear_tsdf(
            t, o0, o1, o2, px, py, clip(cz - 1.0, limit)
        )
        gx, gy, gz = float(gx), float(gy), float(gz)
        length = math.sqrt(gx * gx + gy * gy + gz * gz)
        if not length > 0:
            return np.nan, np.nan, np.nan
        return gx / length, gy / length, gz / length

    @jit_called
    def surface_colour_at(
        colour_volume: Any, o0: int, o1: int, o2: int, cx: float, cy: float, cz: float
    ) -> tuple:
        """RGB at continuous voxel coordinates by trilinear interpolation over the voxels that
        received colour (colour.surface_colour); black where none or outside the grid."""
        n = colour_volume.shape[0]
        if not (cx >= 0 and cx <= n - 1 and cy >= 0 and cy <= n - 1 and cz >= 0 and cz <= n - 1):
            return 0, 0, 0
        bx = min(max(int(math.floor(cx)), 0), n - 2)
        by = min(max(int(math.floor(cy)), 0), n - 2)
        bz = min(max(int(math.floor(cz)), 0), n - 2)
        fx, fy, fz = cx - bx, cy - by, cz - bz
        r = 0.0
        g = 0.0
        b_ = 0.0
        coverage = 0.0
        for a in range(2):
            wa = fx if a else 1.0 - fx
            ia = cell(bx + a, o0, n)
            for b in range(2):
                wb = fy if b else 1.0 - fy
                ib = cell(by + b, o1, n)
                for c in range(2):
                    wc = fz if c else 1.0 - fz
                    ic = cell(bz + c, o2, n)
                    if colour_volume[ia, ib, ic, 3] > 0:
                        w = wa * wb * wc
                        r += w * float(colour_volume[ia, ib, ic, 0])
                        g += w * float(colour_volume[ia, ib, ic, 1])
                        b_ += w * float(colour_volume[ia, ib, ic, 2])
                        coverage += w
        if not coverage > 1e-6:
            return 0, 0, 0
        return (
            min(max(round(r / coverage), 0), 255),
            min(max(round(g / coverage), 0), 255),
            min(max(round(b_ / coverage), 0), 255),
        )

    @jit
    def count_negative(
        tsdf_weight: Any, o0: int, o1: int, o2: int, b0: int, b1: int, b2: int, size: int
    ) -> int:
        """Observed voxels with negative TSDF in the logical block (b0, b1, b2) of size^3 voxels
        (the fine bricks of the cpu raycast, the bricks of the cuda one)."""
        n = tsdf_weight.shape[0]
        count = 0
        for i in range(b0 * size, min((b0 + 1) * size, n)):
            ci = cell(i, o0, n)
            for j in range(b1 * size, min((b1 + 1) * size, n)):
                cj = cell(j, o1, n)
                for k in range(b2 * size, min((b2 + 1) * size, n)):
                    ck = cell(k, o2, n)
                    if tsdf_weight[ci, cj, ck, 0] < 0 and tsdf_weight[ci, cj, ck, 1] > 0:
                        count += 1
        return count

    return SimpleNamespace(
        cell=cell,
        clip=clip,
        count_negative=count_negative,
        dequantise=dequantise,
        gradient_normal=gradient_normal,
        quantise=quantise,
        sample_tsdf_at=sample_tsdf_at,
        surface_colour_at=surface_colour_at,
        trilinear_tsdf=trilinear_tsdf,
    )
