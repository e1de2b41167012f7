# ruff: noqa: ANN001, ANN201  (numba loops: argument types come from the call)
"""kintinuous_ref.preprocess.bilateral_filter on the CPU, each pixel pair weighed once for both
of its pixels (`_bilateral_rows`) with preprocess.ops' float32 weights, tap by tap along rows so
that LLVM vectorises them (preprocess.cpu's other filters run so too).
"""

from __future__ import annotations

import numba
import numpy as np
from llvmlite import ir
from numba import types
from numba.extending import intrinsic

from kintinuous_fast.preprocess.host import inverse_two_variance, spatial_exponents
from kintinuous_fast.preprocess.ops import build_bilateral
from kintinuous_fast.targets import cpu_jit
from kintinuous_fast.targets.cache import register_slowest
from kintinuous_fast.targets.cpu import claimed_items, parallel_part, run_parallel

_inline = numba.njit(cache=True, inline="always")
# FMA contraction only, for the bilateral filter: its weights are float32 approximations anyway
# (1-2 ulp), and contraction makes the polynomial exp cheaper. Functions inlined by numba
# compile with their caller's flags, so the loop that inlines them carries the flag too.
_inline_fma = numba.njit(cache=True, inline="always", fastmath={"contract"})
_parallel_fma = parallel_part(fastmath={"contract"}, _nrt=True)  # its chunks' sums allocate


@intrinsic
def _float32_from_bits(typingctx, bits):
    """The float32 whose IEEE bit pattern is the low 32 bits of the integer `bits`."""
    if not isinstance(bits, types.Integer):
        return None

    def codegen(context, builder, signature, args):
        value = args[0]
        if bits.bitwidth > 32:
            value = builder.trunc(value, ir.IntType(32))
        elif bits.bitwidth < 32:
            value = builder.sext(value, ir.IntType(32))
        return builder.bitcast(value, ir.FloatType())

    return types.float32(bits), codegen


@_inline_fma
def _power_of_two_neg(n):
    """2^-n as float32 by writing its exponent bits: no libm call, so the bilateral loops
    vectorise."""
    return _float32_from_bits((np.int32(127) - n) << 23)


# Inlined into the row loops at numba IR level: as calls, the per-pixel results cost a frame
# about a millisecond more (docs/benchmarks.md, "Numbers behind the fast stages").
_ops = build_bilateral(_inline, _inline_fma, _power_of_two_neg)
exp_neg = _ops.exp_neg
bilateral_weight = _ops.bilateral_weight
bilateral_result = _ops.bilateral_result

# Images with fewer pixels run on the calling thread: waking the second thread costs more than
# such a loop, and on a busy machine a parallel loop waits for its slowest, descheduled thread.
PARALLEL_MIN = 40_000


@_inline_fma
def _pair_weights(centre, neighbour, spatial, inv_two_sigma2, w, wd):
    """For one window offset along a row: the bilateral_weight w of each pixel pair (p, q) and
    wd = w (D(q) - D(p)). Holes hold a far sentinel (`_rows_with_holes_far`), so a pair with
    one hole weighs 0 (two holes do weigh, but only into sums of holes)."""
    for i in range(w.shape[0]):
        difference = neighbour[i] - centre[i]
        weight = bilateral_weight(difference, spatial, inv_two_sigma2)
        w[i] = weight
        wd[i] = weight * difference


@_inline_fma
def _pairs_to_both(centre, neighbour, spatial, inv_two_sigma2, own_w, own_wd, other_w, other_wd):
    """_pair_weights added straight to p's and q's sums (rows that do not overlap)."""
    for i in range(own_w.shape[0]):
        difference = neighbour[i] - centre[i]
        weight = bilateral_weight(difference, spatial, inv_two_sigma2)
        wd = weight * difference
        own_w[i] += weight
        own_wd[i] += wd
        other_w[i] += weight
        other_wd[i] -= wd


@_inline
def _add_pairs(sum_w, sum_wd, w, wd, sign):
    for i in range(w.shape[0]):
        sum_w[i] += w[i]
        sum_wd[i] += wd[i] if sign > 0 else -wd[i]


@_inline
def _bilateral_finish_row(depth, sum_w, sum_wd, extra_w, extra_wd, out):
    """bilateral_result of one row; `extra_*` are the sums another chunk added (zeros where
    none)."""
    for u in range(out.shape[0]):
        w = float(sum_w[u]) + float(extra_w[u])
        wd = float(sum_wd[u]) + float(extra_wd[u])
        out[u] = bilateral_result(depth[u], w, wd)


@_inline
def _rows_with_holes_far(depth, first, stop, hole):
    """depth[first:stop] with its holes (depth <= 0, NaN) at `hole`, a depth so far from
    any valid one that a pair with one hole weighs 0."""
    rows = np.empty((stop - first, depth.shape[1]), np.float32)
    for v in range(first, stop):
        for u in range(depth.shape[1]):
            d = depth[v, u]
            rows[v - first, u] = d if d > 0 else hole
    return rows


@register_slowest("preprocess")
@_parallel_fma
def _bilateral_rows(
    claims, parts, depth, hole, spatial, radius, inv_two_sigma2, chunk_rows, head, tail, out
):
    """The bilateral filter with each pixel pair weighed once.

    The weight of a pixel pair is symmetric, w(p, q) = w(q, p), so every pair with q after p
    (a later row, or the same row to the right) is weighed once and added to both: w (D(q) -
    D(p)) to p's sums and w (D(p) - D(q)) to q's, half the exp() of a per-pixel window. Rows
    are cut into chunks, one part each; a chunk keeps the sums of radius + 1 rows in
    a ring (row v is complete once the pairs starting on it are added) and writes finished rows
    at once. Its first `radius` rows also get pairs from the chunk before: their sums go to
    `head`, the ones it adds below its last row to `tail`, and _bilateral_seams adds the two.
    A chunk reads its rows, and the `radius` rows below them, from a copy of its own in which
    holes hold `hole` (`_rows_with_holes_far`)."""
    height, width = depth.shape
    slots = radius + 1
    zeros = np.zeros(width, np.float32)
    for chunk in claimed_items(claims, head.shape[0], parts):
        first = chunk * chunk_rows
        last = min(height, first + chunk_rows)
        work = _rows_with_holes_far(depth, first, min(height, last + radius), hole)
        ring_w = np.zeros((slots, width), np.float32)
        ring_wd = np.zeros((slots, width), np.float32)
        w = np.empty(width, np.float32)
        wd = np.empty(width, np.float32)
        for v in range(first, last):
            p = v % slots
            for dy in range(0, min(radius, height - 1 - v) + 1):
                y = v + dy
                q = y % slots
                for dx in range(1 if dy == 0 else -radius, radius + 1):
                    lo = max(0, -dx)
                    hi = min(width, width - dx)
                    if hi <= lo:
                        continue
                    if dy > 0:
                        _pairs_to_both(
                            work[v - first, lo:hi],
                            work[y - first, lo + dx : hi + dx],
                            spatial[dy + radius, dx + radius],
                            inv_two_sigma2,
                            ring_w[p, lo:hi],
                            ring_wd[p, lo:hi],
                            ring_w[q, lo + dx : hi + dx],
                            ring_wd[q, lo + dx : hi + dx],
                        )
                        continue
                    # Same row: p's and q's sums overlap, so the weights go through a buffer.
                    count = hi - lo
                    _pair_weights(
                        work[v - first, lo:hi],
                        work[y - first, lo + dx : hi + dx],
                        spatial[dy + radius, dx + radius],
                        inv_two_sigma2,
                        w[:count],
                        wd[:count],
                    )
                    _add_pairs(ring_w[p, lo:hi], ring_wd[p, lo:hi], w[:count], wd[:count], 1)
                    _add_pairs(
                        ring_w[p, lo + dx : hi + dx],
                        ring_wd[p, lo + dx : hi + dx],
                        w[:count],
                        wd[:count],
                        -1,
                    )
            if chunk > 0 and v - first < radius:
                head[chunk, 0, v - first] = ring_w[p]
                head[chunk, 1, v - first] = ring_wd[p]
            else:
                _bilateral_finish_row(depth[v], ring_w[p], ring_wd[p], zeros, zeros, out[v])
            ring_w[p] = 0.0  # the slot of row v + radius + 1 from now on
            ring_wd[p] = 0.0
        for k in range(min(radius, height - last)):
            tail[chunk, 0, k] = ring_w[(last + k) % slots]
            tail[chunk, 1, k] = ring_wd[(last + k) % slots]


@cpu_jit
def _bilateral_seams_loop(depth, chunk_rows, head, tail, out):
    """The first rows of every chunk but the first: their own sums plus the chunk before's."""
    radius = head.shape[2]
    for chunk in range(1, head.shape[0]):
        for k in range(min(radius, depth.shape[0] - chunk * chunk_rows)):
            v = chunk * chunk_rows + k
            _bilateral_finish_row(
                depth[v],
                head[chunk, 0, k],
                head[chunk, 1, k],
                tail[chunk - 1, 0, k],
                tail[chunk - 1, 1, k],
                out[v],
            )


# Rows per chunk of a large image: 15 chunks at 480 rows, enough parts for 16 threads.
CHUNK_ROWS = 32


def bilateral_filter(
    depth: np.ndarray, sigma_space: float, sigma_depth: float, radius: int
) -> np.ndarray:
    """Edge-preserving smoothing of a depth map; holes stay holes (see the reference)."""
    depth = np.ascontiguousarray(depth, dtype=np.float32)
    out = np.empty(depth.shape, dtype=np.float32)
    radius = int(radius)
    spatial = spatial_exponents(sigma_space, radius)
    inv_two_sigma2 = inverse_two_variance(sigma_depth)
    # Holes (and NaN) as a depth farther than 12.65 sigma_d from any valid one: x > 80 (weight 0).
    hole = np.float32(-(16.0 * sigma_depth + 1.0))
    height, width = depth.shape
    # Chunks of a fixed height, not a number per thread: a seam row's sums are added in another
    # order than an inner row's, so chunks that followed the thread count would make the result
    # depend on it. At least `radius` rows each, so only one chunk reaches into the next.
    chunk_rows = height if depth.size < PARALLEL_MIN else CHUNK_ROWS
    chunk_rows = max(radius, chunk_rows, 1)
    chunks = -(-height // chunk_rows)
    head = np.empty((chunks, 2, radius, width), np.float32)
    tail = np.empty((chunks, 2, radius, width), np.float32)
    run_parallel(
        _bilateral_rows,
        depth,
        hole,
        spatial,
        radius,
        inv_two_sigma2,
        chunk_rows,
        head,
        tail,
        out,
        parts=chunks,
    )
    _bilateral_seams_loop(depth, chunk_rows, head, tail, out)
    return out
