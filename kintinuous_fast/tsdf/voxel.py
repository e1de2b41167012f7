"""The stored voxels, written once for the CPU and the CUDA target: quantisation, the cyclical
buffer's cells, and sampling (trilinear TSDF, its gradient, surface colour) that the raycast and
the moving volume share. Integration (tsdf.ops) and the march (raycast.ops) build on them.

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
# Voxels per side of the fine bricks whose observed negative voxels integration marks in a bit
# mask per brick (the cpu raycast's second level of empty-space skipping, inside the bricks
# next to a surface; fine_voxel_bit assumes 2).
FINE = 2

# Cyclical buffer (kintinuous_ref.tsdf, moving volume): logical voxel l lives in array cell
# (l + offset) mod N, offset in [0, N). Every function below takes the offset as three ints
# (o0, o1, o2) and maps logical indices with `cell` (one compare, no division).


def build_ops(
    jit: Callable[[Any], Any],
    jit_called: Callable[[Any], Any] | None = None,
    dequantise_table: bool = False,
) -> SimpleNamespace:
    """The voxel functions compiled with `jit`, but the small scalar helpers and the per-ray normal
    and colour with `jit_called` (default `jit`), in one namespace. Integration passes one decorator
    that inlines everything at numba IR level: its per-voxel loops need that to vectorise
    (docs/benchmarks.md, "Numbers behind the fast stages"). The cpu raycast passes plain calls
    without reference counting as `jit_called`: LLVM still inlines the small helpers, so the march
    is as fast and bit-identical, and numba does not type them again at every call site (which makes
    its raycast loop compile several times as long). The trilinear sample and the gradient stay
    numba inlines there: as calls that LLVM keeps, the cpu raycast is slower (docs/benchmarks.md,
    "Numbers behind the fast stages"). With `dequantise_table`, dequantise reads its (equal) values
    from a table of all 65536 (256 KiB): a load instead of three conversions and a multiply, which
    pays in the cpu raycast (its samples and normals dequantise ~80 values per ray) but not in cpu
    integration, one value per updated voxel: it keeps the arithmetic, and so does CUDA, whose
    constant memory holds 64 KiB (docs/benchmarks.md, "Numbers behind the fast stages")."""
    jit_called = jit_called or jit
    storage = build_storage(jit_called, dequantise_table)
    sampling = build_sampling(jit, jit_called, storage)
    interior = _build_interior_gradient(jit, jit_called, storage)
    normals = build_normals(jit, jit_called, sampling, interior)
    colour = build_surface_colour(jit_called, storage)
    negatives = build_negatives(jit, storage)
    parts = (storage, sampling, interior, normals, colour, negatives)
    return SimpleNamespace(**{name: f for part in parts for name, f in vars(part).items()})


def build_storage(jit_called: Callable[[Any], Any], dequantise_table: bool) -> SimpleNamespace:
    """The stored int16 TSDF to and from floats, and the cells of the cyclical buffer."""

    if dequantise_table:
        # the same products as below, for every int16; numba freezes the closure's table into
        # the compiled code as a constant
        table = (np.arange(-32768, 32768) * TSDF_INVERSE_SCALE).astype(np.float32)

        @jit_called
        def dequantise(q: Any) -> Any:
            """The arithmetic dequantise's value, read from the table of every int16."""
            return table[np.intp(q) + 32768]

    else:

        @jit_called
        def dequantise(q: Any) -> Any:
            """float32 TSDF of a stored int16: q / 32767 correctly rounded to float32, the
            division to_reference_volume does. Computed as a float64 product (a float32
            division costs ~4x a multiply, and the raycast's normals take 48 of them): its
            error (~1e-16 relative) is far below the gap between q / 32767 and any float32
            rounding midpoint (> 2^-39 relative, as 32767 is odd), so it rounds the same way;
            checked for every int16 by the tests."""
            return np.float32(float(q) * TSDF_INVERSE_SCALE)

    @jit_called
    def quantise(f: Any) -> int:
        """Nearest int16 of F * 32767, F in [-1, 1]."""
        q = round(float(f) * TSDF_SCALE)
        return min(max(q, -32767), 32767)

    @jit_called
    def cell(index: int, offset: int, n: int) -> int:
        """Array cell of logical index `index` in [0, N) with buffer offset in [0, N), unsigned:
        numba then indexes without its negative-index wraparound (a compare and select per
        index, which also keeps LLVM from vectorising)."""
        c = index + offset
        return np.uint64(c - n if c >= n else c)

    return SimpleNamespace(cell=cell, dequantise=dequantise, quantise=quantise)


def build_sampling(
    jit: Callable[[Any], Any], jit_called: Callable[[Any], Any], storage: SimpleNamespace
) -> SimpleNamespace:
    """Trilinear TSDF samples: over the observed voxels (the march's), and plain (normals')."""
    cell, dequantise = storage.cell, storage.dequantise

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
        i0, i1 = cell(bx, o0, n), cell(bx + 1, o0, n)
        j0, j1 = cell(by, o1, n), cell(by + 1, o1, n)
        k0, k1 = cell(bz, o2, n), cell(bz + 1, o2, n)
        gx, gy, gz = 1.0 - fx, 1.0 - fy, 1.0 - fz
        t = tsdf_weight
        # Summed as trees, not in a chain of eight: the march waits on every sample, and a
        # chain would add its latency to each.
        w000, p000 = observed_corner(t, i0, j0, k0, gx * gy * gz)
        w001, p001 = observed_corner(t, i0, j0, k1, gx * gy * fz)
        w010, p010 = observed_corner(t, i0, j1, k0, gx * fy * gz)
        w011, p011 = observed_corner(t, i0, j1, k1, gx * fy * fz)
        w100, p100 = observed_corner(t, i1, j0, k0, fx * gy * gz)
        w101, p101 = observed_corner(t, i1, j0, k1, fx * gy * fz)
        w110, p110 = observed_corner(t, i1, j1, k0, fx * fy * gz)
        w111, p111 = observed_corner(t, i1, j1, k1, fx * fy * fz)
        total = ((p000 + p001) + (p010 + p011)) + ((p100 + p101) + (p110 + p111))
        coverage = ((w000 + w001) + (w010 + w011)) + ((w100 + w101) + (w110 + w111))
        if not coverage > 1e-6:
            return np.nan
        return total / coverage

    @jit_called
    def observed_corner(tsdf_weight: Any, i: int, j: int, k: int, weight: float) -> tuple:
        """(weight, weight * F) of stored voxel (i, j, k), or (0, 0) when it is unobserved
        (branch free: both loads share a cache line)."""
        value = float(dequantise(tsdf_weight[i, j, k, 0]))
        observed = weight if tsdf_weight[i, j, k, 1] > 0 else 0.0
        return observed, observed * value

    @jit_called
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

    @jit_called
    def clip(c: float, limit: float) -> float:
        return min(max(c, 0.0), limit)

    return SimpleNamespace(
        clip=clip,
        observed_corner=observed_corner,
        sample_tsdf_at=sample_tsdf_at,
        trilinear_tsdf=trilinear_tsdf,
    )


def _build_interior_gradient(
    jit: Callable[[Any], Any], jit_called: Callable[[Any], Any], storage: SimpleNamespace
) -> SimpleNamespace:
    """The TSDF gradient inside the grid's one-voxel border, from stored values."""
    cell = storage.cell

    @jit
    def interior_gradient(
        tsdf_weight: Any, o0: int, o1: int, o2: int, cx: float, cy: float, cz: float
    ) -> tuple:
        """The TSDF gradient (ahead - behind per axis, as clipped_gradient) at a point with
        1 <= c < N - 2 on every axis, in stored int16 units (a normal does not depend on the
        scale). Samples at c +- 1 have c's fractions, so T(c + e) - T(c - e) is the trilinear
        blend of v(i + 1) - v(i - 1): 32 stored values instead of 48 samples' corners, and
        no dequantising. Equal to the six samples' difference up to their float32 rounding
        (~1e-7 of the gradient)."""
        n = tsdf_weight.shape[0]
        bx, by, bz = int(math.floor(cx)), int(math.floor(cy)), int(math.floor(cz))
        fx, fy, fz = cx - bx, cy - by, cz - bz
        x0, x1, x2, x3 = four_cells(bx, o0, n)
        y0, y1, y2, y3 = four_cells(by, o1, n)
        z0, z1, z2, z3 = four_cells(bz, o2, n)
        t = tsdf_weight
        gx = bilinear(
            fy, fz,
            difference(t[x0, y1, z1, 0], t[x1, y1, z1, 0], t[x2, y1, z1, 0], t[x3, y1, z1, 0], fx),
            difference(t[x0, y1, z2, 0], t[x1, y1, z2, 0], t[x2, y1, z2, 0], t[x3, y1, z2, 0], fx),
            difference(t[x0, y2, z1, 0], t[x1, y2, z1, 0], t[x2, y2, z1, 0], t[x3, y2, z1, 0], fx),
            difference(t[x0, y2, z2, 0], t[x1, y2, z2, 0], t[x2, y2, z2, 0], t[x3, y2, z2, 0], fx),
        )  # fmt: skip
        gy = bilinear(
            fx, fz,
            difference(t[x1, y0, z1, 0], t[x1, y1, z1, 0], t[x1, y2, z1, 0], t[x1, y3, z1, 0], fy),
            difference(t[x1, y0, z2, 0], t[x1, y1, z2, 0], t[x1, y2, z2, 0], t[x1, y3, z2, 0], fy),
            difference(t[x2, y0, z1, 0], t[x2, y1, z1, 0], t[x2, y2, z1, 0], t[x2, y3, z1, 0], fy),
            difference(t[x2, y0, z2, 0], t[x2, y1, z2, 0], t[x2, y2, z2, 0], t[x2, y3, z2, 0], fy),
        )  # fmt: skip
        gz = bilinear(
            fx, fy,
            difference(t[x1, y1, z0, 0], t[x1, y1, z1, 0], t[x1, y1, z2, 0], t[x1, y1, z3, 0], fz),
            difference(t[x1, y2, z0, 0], t[x1, y2, z1, 0], t[x1, y2, z2, 0], t[x1, y2, z3, 0], fz),
            difference(t[x2, y1, z0, 0], t[x2, y1, z1, 0], t[x2, y1, z2, 0], t[x2, y1, z3, 0], fz),
            difference(t[x2, y2, z0, 0], t[x2, y2, z1, 0], t[x2, y2, z2, 0], t[x2, y2, z3, 0], fz),
        )  # fmt: skip
        return gx, gy, gz

    @jit_called
    def four_cells(index: int, offset: int, n: int) -> tuple:
        """The cells of logical indices index - 1 .. index + 2."""
        return (
            cell(index - 1, offset, n),
            cell(index, offset, n),
            cell(index + 1, offset, n),
            cell(index + 2, offset, n),
        )

    @jit_called
    def difference(v0: int, v1: int, v2: int, v3: int, f: float) -> float:
        """T(c + 1) - T(c - 1) along one axis from the stored values at floor(c) - 1 .. + 2."""
        return (1.0 - f) * float(np.int32(v2) - np.int32(v0)) + f * float(
            np.int32(v3) - np.int32(v1)
        )

    @jit_called
    def bilinear(f: float, g: float, d00: float, d01: float, d10: float, d11: float) -> float:
        """Bilinear blend of values at the corners (0, 0), (0, 1), (1, 0), (1, 1)."""
        return (1.0 - f) * ((1.0 - g) * d00 + g * d01) + f * ((1.0 - g) * d10 + g * d11)

    return SimpleNamespace(
        bilinear=bilinear,
        difference=difference,
        four_cells=four_cells,
        interior_gradient=interior_gradient,
    )


def build_normals(
    jit: Callable[[Any], Any],
    jit_called: Callable[[Any], Any],
    sampling: SimpleNamespace,
    interior: SimpleNamespace,
) -> SimpleNamespace:
    """Unit TSDF-gradient normals (the raycast's), at one point or two."""
    clip, trilinear_tsdf = sampling.clip, sampling.trilinear_tsdf
    interior_gradient = interior.interior_gradient

    @jit_called
    def gradient_normal(
        tsdf_weight: Any, o0: int, o1: int, o2: int, cx: float, cy: float, cz: float
    ) -> tuple:
        """Unit TSDF gradient by central differences one voxel apart (raycast._gradient_normals);
        NaN when it vanishes. Inside the grid's one-voxel border the six trilinear samples
        share their fractions, so each difference is one trilinear blend of differences of
        stored values (interior_gradient); at the border, six clipped samples as the reference."""
        if in_interior(cx, cy, cz, tsdf_weight.shape[0]):
            gx, gy, gz = interior_gradient(tsdf_weight, o0, o1, o2, cx, cy, cz)
        else:
            gx, gy, gz = clipped_gradient(tsdf_weight, o0, o1, o2, cx, cy, cz)
        return unit_or_nan(gx, gy, gz)

    @jit_called
    def gradient_normals(
        tsdf_weight: Any,
        o0: int,
        o1: int,
        o2: int,
        ax: float,
        ay: float,
        az: float,
        bx: float,
        by: float,
        bz: float,
    ) -> tuple:
        """gradient_normal at two points (a then b, six components). When both lie inside the
        border, their two interior gradients are one stretch of code: independent loads and
        arithmetic that the core overlaps (the cpu raycast's pairs of rays take their normals
        here)."""
        n = tsdf_weight.shape[0]
        if in_interior(ax, ay, az, n) and in_interior(bx, by, bz, n):
            ga = interior_gradient(tsdf_weight, o0, o1, o2, ax, ay, az)
            gb = interior_gradient(tsdf_weight, o0, o1, o2, bx, by, bz)
            na, nb = unit_or_nan(ga[0], ga[1], ga[2]), unit_or_nan(gb[0], gb[1], gb[2])
        else:
            na = gradient_normal(tsdf_weight, o0, o1, o2, ax, ay, az)
            nb = gradient_normal(tsdf_weight, o0, o1, o2, bx, by, bz)
        return na[0], na[1], na[2], nb[0], nb[1], nb[2]

    @jit_called
    def in_interior(cx: float, cy: float, cz: float, n: int) -> bool:
        """Whether 1 <= c < N - 2 on every axis (interior_gradient's domain)."""
        return cx >= 1 and cx < n - 2 and cy >= 1 and cy < n - 2 and cz >= 1 and cz < n - 2

    @jit_called
    def unit_or_nan(gx: float, gy: float, gz: float) -> tuple:
        """g / |g|, NaN when g vanishes."""
        length = math.sqrt(gx * gx + gy * gy + gz * gz)
        if not length > 0:
            return np.nan, np.nan, np.nan
        scale = 1.0 / length  # one division, not three (within an ulp)
        return gx * scale, gy * scale, gz * scale

    @jit
    def clipped_gradient(
        tsdf_weight: Any, o0: int, o1: int, o2: int, cx: float, cy: float, cz: float
    ) -> tuple:
        """The TSDF gradient from six trilinear samples at c +- 1 per axis, clipped to the grid
        (raycast._gradient_normals), in normalised TSDF units."""
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
        return float(gx), float(gy), float(gz)

    return SimpleNamespace(
        clipped_gradient=clipped_gradient,
        gradient_normal=gradient_normal,
        gradient_normals=gradient_normals,
        in_interior=in_interior,
        unit_or_nan=unit_or_nan,
    )


def build_surface_colour(
    jit_called: Callable[[Any], Any], storage: SimpleNamespace
) -> SimpleNamespace:
    """The colour volume's trilinear colour at a point."""
    cell = storage.cell

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

    return SimpleNamespace(surface_colour_at=surface_colour_at)


def build_negatives(jit: Callable[[Any], Any], storage: SimpleNamespace) -> SimpleNamespace:
    """Observed voxels with negative TSDF, counted per brick or marked per fine brick (the
    raycast's empty-space maps)."""
    cell = storage.cell

    @jit
    def count_negative(
        tsdf_weight: Any, o0: int, o1: int, o2: int, b0: int, b1: int, b2: int, size: int
    ) -> int:
        """Observed voxels with negative TSDF in the logical block (b0, b1, b2) of size^3 voxels
        (the bricks of the cuda raycast's empty-space map)."""
        n = tsdf_weight.shape[0]
        count = 0
        for i in range(b0 * size, min((b0 + 1) * size, n)):
            ci = cell(i, o0, n)
            for j in range(b1 * size, min((b1 + 1) * size, n)):
                cj = cell(j, o1, n)
                for k in range(b2 * size, min((b2 + 1) * size, n)):
                    if observed_negative(tsdf_weight, ci, cj, cell(k, o2, n)):
                        count += 1
        return count

    @jit
    def negative_mask(
        tsdf_weight: Any, o0: int, o1: int, o2: int, f0: int, f1: int, f2: int
    ) -> int:
        """Bit mask (fine_voxel_bit) of the observed voxels with negative TSDF in the logical
        fine brick (f0, f1, f2) (the cpu raycast's NegativeMasks)."""
        n = tsdf_weight.shape[0]
        mask = 0
        for i in range(f0 * FINE, min((f0 + 1) * FINE, n)):
            ci = cell(i, o0, n)
            for j in range(f1 * FINE, min((f1 + 1) * FINE, n)):
                cj = cell(j, o1, n)
                for k in range(f2 * FINE, min((f2 + 1) * FINE, n)):
                    if observed_negative(tsdf_weight, ci, cj, cell(k, o2, n)):
                        mask |= fine_voxel_bit(i, j, k)
        return mask

    @jit
    def observed_negative(tsdf_weight: Any, ci: int, cj: int, ck: int) -> bool:
        return tsdf_weight[ci, cj, ck, 0] < 0 and tsdf_weight[ci, cj, ck, 1] > 0

    @jit
    def fine_voxel_bit(i: int, j: int, k: int) -> int:
        """Logical voxel (i, j, k)'s bit in its fine brick's mask: bit 4 a + 2 b + c for its
        place (a, b, c) = (i, j, k) mod 2 in the brick (FINE = 2: 8 voxels, 8 bits)."""
        return 1 << (((i & 1) << 2) | ((j & 1) << 1) | (k & 1))

    return SimpleNamespace(
        count_negative=count_negative,
        fine_voxel_bit=fine_voxel_bit,
        negative_mask=negative_mask,
        observed_negative=observed_negative,
    )
