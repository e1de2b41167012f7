# ruff: noqa: ANN001, ANN201  (numba kernels and loops: argument types come from the call)
"""kintinuous_ref.preprocess on the CPU: loops over rows, on all threads, around each stage's ops.

Same names, signatures and results as the reference (see tests/test_fast_preprocess.py for the
stated tolerances); arrays are NumPy arrays.

Speed (target: the whole stage in ~20 ms per 640x480 frame on two cores). Every image loop
here runs over a contiguous slice of a row with a straight-line body, which LLVM turns into SIMD
code; a per-pixel call into the 2-D `*_pixel` ops (`depth[v + dy, u + dx]` with a possibly
negative index) does not vectorise, as numba must wrap negative indices. So the filters are
written as "for each tap, for each pixel of the row", calling ops.py's per-tap and per-result
functions on row slices; every pixel's taps are summed in the reference's order, so the results
are bit-identical where the reference's arithmetic is repeated (pyramids, gradients, vertices,
normals, masks). The bilateral filter weighs each pixel pair once for both of its pixels
(`_bilateral_rows`), with ops.py's float32 weights.
"""

from __future__ import annotations

import numba
import numpy as np
from llvmlite import ir
from numba import types
from numba.extending import intrinsic

from kintinuous_fast.preprocess.host import (
    SOBEL_X,
    SOBEL_Y,
    gaussian3x3,
    inverse_two_variance,
    preprocess_frame_with,
    spatial_exponents,
)
from kintinuous_fast.preprocess.ops import build_ops
from kintinuous_fast.targets import cpu_jit, pinhole
from kintinuous_fast.targets.cpu import (
    claimed_items,
    parallel_part,
    run_parallel,
    run_parallel_above,
)
from kintinuous_ref.camera import Intrinsics
from kintinuous_ref.config import PreprocessConfig
from kintinuous_ref.preprocess import (
    PreprocessedFrame,
    PyramidLevel,
    check_frame_inputs,
    model_pyramid,
)

__all__ = [
    "PreprocessedFrame",
    "PyramidLevel",
    "bilateral_filter",
    "discontinuity_mask",
    "intensity_gradients",
    "intensity_image",
    "metric_depth",
    "model_pyramid",
    "normal_map",
    "preprocess_frame",
    "pyramid_down_depth",
    "pyramid_down_intensity",
    "vertex_map",
]

_parallel = parallel_part()
_parallel_allocating = parallel_part(_nrt=True)  # for loops with row buffers of their own
_inline = numba.njit(cache=True, inline="always")
# FMA contraction only, for the bilateral filter: its weights are float32 approximations anyway
# (1-2 ulp), and contraction makes the polynomial exp a third cheaper. Functions inlined by numba
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


# The ops are inlined into the row loops at numba IR level: compiled as calls, they made a
# 640x480 frame ~1 ms slower (the bilateral filter's per-pixel results above all).
_ops = build_ops(_inline, _inline_fma, _power_of_two_neg)
# Module-level names: numba resolves the scalar functions as globals of the loops below.
metric_value = _ops.metric_value
exp_neg = _ops.exp_neg
bilateral_weight = _ops.bilateral_weight
bilateral_result = _ops.bilateral_result
binomial5 = _ops.binomial5
depth_tap_counts = _ops.depth_tap_counts
pyrdown_depth_result = _ops.pyrdown_depth_result
vertex_from_depth = _ops.vertex_from_depth
normal_from_edges = _ops.normal_from_edges
intensity_pixel = _ops.intensity_pixel
correlate3x3_pixel = _ops.correlate3x3_pixel
is_depth_jump = _ops.is_depth_jump
colour_fusable = _ops.colour_fusable

# Images with fewer pixels run on the calling thread: waking the second thread costs more than
# such a loop, and on a busy machine a parallel loop waits for its slowest, descheduled thread.
PARALLEL_MIN = 40_000


def _run(loop, pixels: int, *args) -> None:
    """run_parallel a loop, on the calling thread alone below PARALLEL_MIN pixels."""
    run_parallel_above(PARALLEL_MIN, loop, pixels, *args)


# ----------------------------------------------------------------------------------------------
# Row kernels (one output row; slices start at the first pixel so every index is >= 0)


@_inline_fma
def _pair_weights(centre, neighbour, spatial, inv_two_sigma2, w, wd):
    """For one window offset along a row: the bilateral_weight w of each pixel pair (p, q) and
    wd = w (D(q) - D(p)). Holes hold a far sentinel (bilateral_filter's `work`), so a pair with
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


@_parallel_fma
def _bilateral_rows(
    claims, parts, work, depth, spatial, radius, inv_two_sigma2, chunk_rows, head, tail, out
):
    """The bilateral filter with each pixel pair weighed once.

    The weight of a pixel pair is symmetric, w(p, q) = w(q, p), so every pair with q after p
    (a later row, or the same row to the right) is weighed once and added to both: w (D(q) -
    D(p)) to p's sums and w (D(p) - D(q)) to q's, half the exp() of a per-pixel window. Rows
    are cut into chunks, one part each; a chunk keeps the sums of radius + 1 rows in
    a ring (row v is complete once the pairs starting on it are added) and writes finished rows
    at once. Its first `radius` rows also get pairs from the chunk before: their sums go to
    `head`, the ones it adds below its last row to `tail`, and _bilateral_seams adds the two."""
    height, width = work.shape
    slots = radius + 1
    zeros = np.zeros(width, np.float32)
    for chunk in claimed_items(claims, head.shape[0], parts):
        first = chunk * chunk_rows
        last = min(height, first + chunk_rows)
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
                            work[v, lo:hi],
                            work[y, lo + dx : hi + dx],
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
                        work[v, lo:hi],
                        work[y, lo + dx : hi + dx],
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


@_parallel
def _split_columns(claims, parts, image, even, odd):
    """even[v, i] = image[v, 2i], odd[v, i] = image[v, 2i + 1]: the 5x5 taps of a half-size
    pixel u are then contiguous runs (columns 2u + dx: even[u - 1], odd[u - 1], even[u], odd[u],
    even[u + 1]), which vectorise; stride-2 loads do not."""
    pairs = odd.shape[1]
    for v in claimed_items(claims, image.shape[0], parts):
        row = image[v]
        row_even = even[v]
        row_odd = odd[v]
        for i in range(pairs):  # one pass over both: an interleaved load LLVM vectorises
            row_even[i] = row[2 * i]
            row_odd[i] = row[2 * i + 1]
        if even.shape[1] > pairs:  # odd width: the last column has no odd partner
            row_even[pairs] = row[2 * pairs]


@_inline
def _tap_columns(dx, out_width, width):
    """Half-size pixels [lo, hi) whose tap 2u + dx lies inside the row, and the offset of that
    tap's run in `even` (dx even) or `odd` (dx odd): column 2u + dx is entry u + dx // 2."""
    lo = (max(0, -dx) + 1) // 2
    hi = min(out_width, (width - 1 - dx) // 2 + 1)
    return lo, max(hi, lo), lo + dx // 2


@_inline
def _pyrdown_depth_taps(centre, neighbour, cutoff, w, total, weights):
    """One tap of the edge-aware 5x5 Gaussian for a run of half-size pixels (float64)."""
    for i in range(total.shape[0]):
        n = float(neighbour[i])
        use = depth_tap_counts(float(centre[i]), n, cutoff)
        total[i] += w * n if use else 0.0
        weights[i] += w if use else 0.0


@_parallel_allocating
def _pyrdown_depth_rows(claims, parts, even, odd, width, cutoff, out):
    """pyramid_down_depth: taps summed in the reference's order (dy, then dx) in float64, so
    the result is the reference's to the bit."""
    height = even.shape[0]
    out_height, out_width = out.shape
    for v in claimed_items(claims, out_height, parts):
        total = np.zeros(out_width)
        weights = np.zeros(out_width)
        centre = even[2 * v]
        for dy in range(-2, 3):
            y = 2 * v + dy
            if y < 0 or y >= height:
                continue
            for dx in range(-2, 3):
                lo, hi, start = _tap_columns(dx, out_width, width)
                source = even[y] if dx % 2 == 0 else odd[y]
                _pyrdown_depth_taps(
                    centre[lo:hi],
                    source[start : start + hi - lo],
                    cutoff,
                    binomial5(dy) * binomial5(dx),
                    total[lo:hi],
                    weights[lo:hi],
                )
        for u in range(out_width):
            out[v, u] = pyrdown_depth_result(float(centre[u]), total[u], weights[u])


@_inline
def _pyrdown_intensity_taps(neighbour, w, total, weights):
    for i in range(total.shape[0]):
        total[i] += w * float(neighbour[i])
        weights[i] += w


@_parallel_allocating
def _pyrdown_intensity_rows(claims, parts, even, odd, width, out):
    """pyramid_down_intensity: 5x5 Gaussian renormalised over the taps inside the image."""
    height = even.shape[0]
    out_height, out_width = out.shape
    for v in claimed_items(claims, out_height, parts):
        total = np.zeros(out_width)
        weights = np.zeros(out_width)
        for dy in range(-2, 3):
            y = 2 * v + dy
            if y < 0 or y >= height:
                continue
            for dx in range(-2, 3):
                lo, hi, start = _tap_columns(dx, out_width, width)
                source = even[y] if dx % 2 == 0 else odd[y]
                _pyrdown_intensity_taps(
                    source[start : start + hi - lo],
                    binomial5(dy) * binomial5(dx),
                    total[lo:hi],
                    weights[lo:hi],
                )
        for u in range(out_width):
            out[v, u] = np.float32(total[u] / weights[u])


@_inline
def _vertex_row(depth, v, camera, out):
    """Vertices of one row as float32 (x, y, z) triples (vertex_from_depth)."""
    for u in range(depth.shape[0]):
        x, y, z = vertex_from_depth(float(depth[u]), u, v, camera)
        out[3 * u] = np.float32(x)
        out[3 * u + 1] = np.float32(y)
        out[3 * u + 2] = np.float32(z)


@_parallel
def _vertex_rows(claims, parts, depth, camera, out):
    height, width = depth.shape
    flat = out.reshape((height, 3 * width))
    for v in claimed_items(claims, height, parts):
        _vertex_row(depth[v], v, camera, flat[v])


@_inline
def _normal_row(here, below, out):
    """normal_from_edges for the pixels of a row that have a right and a lower neighbour; rows
    are flat float32 (x, y, z) triples."""
    for u in range(out.shape[0] // 3 - 1):
        p0 = here[3 * u]
        p1 = here[3 * u + 1]
        p2 = here[3 * u + 2]
        n0, n1, n2 = normal_from_edges(
            below[3 * u] - p0,
            below[3 * u + 1] - p1,
            below[3 * u + 2] - p2,
            here[3 * u + 3] - p0,
            here[3 * u + 4] - p1,
            here[3 * u + 5] - p2,
        )
        out[3 * u] = n0
        out[3 * u + 1] = n1
        out[3 * u + 2] = n2


@_parallel
def _normal_rows(claims, parts, vertices, out):
    """normal_map; float32 throughout, as the reference's np.cross/norm."""
    height, width = vertices.shape[0], vertices.shape[1]
    flat = vertices.reshape((height, 3 * width))
    flat_out = out.reshape((height, 3 * width))
    for v in claimed_items(claims, height, parts):
        row = flat_out[v]
        if v + 1 < height and width > 0:
            _normal_row(flat[v], flat[v + 1], row)
        for u in range(0 if v + 1 >= height else max(width - 1, 0), width):
            row[3 * u] = np.float32(np.nan)  # no lower or right neighbour
            row[3 * u + 1] = np.float32(np.nan)
            row[3 * u + 2] = np.float32(np.nan)


@_parallel
def _intensity_rows(claims, parts, colour, out):
    height, width = out.shape
    flat = colour.reshape((height, 3 * width))
    for v in claimed_items(claims, height, parts):
        row = flat[v]
        for u in range(width):
            out[v, u] = intensity_pixel(row[3 * u], row[3 * u + 1], row[3 * u + 2])


@_inline
def _correlate_row(image, v, kernel, out):
    """One row of a 3x3 correlation with replicated borders, each pixel's nine products summed
    in the reference's order (kernel row, then column) in float64."""
    height, width = image.shape
    for dy in range(3):
        y = min(max(v + dy - 1, 0), height - 1)
        row = image[y]
        for dx in range(3):
            k = kernel[dy, dx]
            tap = row[dx:]
            inner = out[1 : width - 1]  # pixel u = i + 1 reads row[u - 1 + dx] = tap[i]
            if dy == 0 and dx == 0:
                for i in range(width - 2):
                    inner[i] = k * float(tap[i])
            else:
                for i in range(width - 2):
                    inner[i] += k * float(tap[i])
    # The two border columns: the scalar op clamps their outside neighbour.
    out[0] = correlate3x3_pixel(image, v, 0, kernel)
    out[width - 1] = correlate3x3_pixel(image, v, width - 1, kernel)


@_parallel
def _blur_rows(claims, parts, intensity, blur, blurred):
    for v in claimed_items(claims, intensity.shape[0], parts):
        _correlate_row(intensity, v, blur, blurred[v])


@_parallel_allocating
def _sobel_rows(claims, parts, blurred, sobel_x, sobel_y, dx, dy):
    width = blurred.shape[1]
    for v in claimed_items(claims, blurred.shape[0], parts):
        row = np.empty(width)
        _correlate_row(blurred, v, sobel_x, row)
        for u in range(width):
            dx[v, u] = np.float32(row[u])
        _correlate_row(blurred, v, sobel_y, row)
        for u in range(width):
            dy[v, u] = np.float32(row[u])


@_inline
def _count_jumps(centre, neighbour, jump, bad):
    """+1 where is_depth_jump."""
    for i in range(centre.shape[0]):
        bad[i] += np.int32(is_depth_jump(centre[i], neighbour[i], jump))


@_parallel_allocating
def _discontinuity_rows(claims, parts, depth, radius, jump, max_bad, out):
    height, width = depth.shape
    for v in claimed_items(claims, height, parts):
        bad = np.zeros(width, np.int32)
        centre = depth[v]
        for dy in range(-radius, radius + 1):
            y = v + dy
            if y < 0 or y >= height:
                continue
            for dx in range(-radius, radius + 1):
                if dy == 0 and dx == 0:
                    continue
                lo = max(0, -dx)
                hi = min(width, width - dx)
                if hi <= lo:
                    continue
                _count_jumps(centre[lo:hi], depth[y, lo + dx : hi + dx], jump, bad[lo:hi])
        for u in range(width):
            out[v, u] = colour_fusable(centre[u], bad[u], max_bad)


@_parallel
def _metric_depth_rows(claims, parts, raw, integer, depth_scale, max_depth, out):
    for v in claimed_items(claims, raw.shape[0], parts):
        for u in range(raw.shape[1]):
            out[v, u] = metric_value(raw[v, u], integer, depth_scale, max_depth)


# ----------------------------------------------------------------------------------------------
# Public functions: kintinuous_ref.preprocess's signatures


def metric_depth(depth: np.ndarray, max_depth: float, depth_scale: float = 5000.0) -> np.ndarray:
    """float32 metres, 0 where NaN, <= 0 or farther than max_depth (integers: raw units)."""
    depth = np.ascontiguousarray(depth)
    integer = bool(np.issubdtype(depth.dtype, np.integer))
    if not integer and depth.dtype != np.float32:
        depth = depth.astype(np.float32)  # the reference's cast, before any comparison
    out = np.empty(depth.shape, dtype=np.float32)
    _run(
        _metric_depth_rows,
        depth.size,
        depth,
        integer,
        np.float32(depth_scale),
        np.float32(max_depth),
        out,
    )
    return out


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
    work = np.where(depth > 0, depth, hole).astype(np.float32)
    height, width = depth.shape
    # A few chunks per thread; at least `radius` rows each, so only one chunk reaches into the next.
    chunks = 1 if depth.size < PARALLEL_MIN else 4 * numba.get_num_threads()
    chunk_rows = max(radius, -(-height // chunks), 1)
    chunks = -(-height // chunk_rows)
    head = np.empty((chunks, 2, radius, width), np.float32)
    tail = np.empty((chunks, 2, radius, width), np.float32)
    run_parallel(
        _bilateral_rows,
        work,
        depth,
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


def _split(image: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Even and odd columns of a float32 image (see _split_columns)."""
    image = np.ascontiguousarray(image, dtype=np.float32)
    height, width = image.shape
    even = np.empty((height, (width + 1) // 2), np.float32)
    odd = np.empty((height, width // 2), np.float32)
    _run(_split_columns, image.size, image, even, odd)
    return even, odd


def pyramid_down_depth(depth: np.ndarray, cutoff: float) -> np.ndarray:
    """Half-size depth by the edge-aware 5x5 Gaussian centred on each even pixel."""
    even, odd = _split(depth)
    out = np.empty((depth.shape[0] // 2, depth.shape[1] // 2), dtype=np.float32)
    _run(_pyrdown_depth_rows, depth.size, even, odd, depth.shape[1], float(cutoff), out)
    return out


def pyramid_down_intensity(image: np.ndarray) -> np.ndarray:
    """Half-size image by the 5x5 Gaussian, weights renormalised at the border."""
    even, odd = _split(image)
    out = np.empty((image.shape[0] // 2, image.shape[1] // 2), dtype=np.float32)
    _run(_pyrdown_intensity_rows, image.size, even, odd, image.shape[1], out)
    return out


def vertex_map(depth: np.ndarray, camera: Intrinsics) -> np.ndarray:
    """Camera-frame points D K^-1 [u, v, 1]; NaN where D <= 0."""
    depth = np.ascontiguousarray(depth, dtype=np.float32)
    out = np.empty((*depth.shape, 3), dtype=np.float32)
    _run(_vertex_rows, depth.size, depth, pinhole(camera), out)
    return out


def normal_map(vertices: np.ndarray) -> np.ndarray:
    """Unit normals from neighbour differences, pointing to the camera; NaN where undefined."""
    vertices = np.ascontiguousarray(vertices, dtype=np.float32)
    out = np.empty(vertices.shape, dtype=np.float32)
    _run(_normal_rows, vertices.shape[0] * vertices.shape[1], vertices, out)
    return out


def intensity_image(colour: np.ndarray) -> np.ndarray:
    """I = 0.299 R + 0.587 G + 0.114 B, float32 in 0..255."""
    colour = np.ascontiguousarray(colour)
    out = np.empty(colour.shape[:2], dtype=np.float32)
    _run(_intensity_rows, out.size, colour, out)
    return out


def intensity_gradients(intensity: np.ndarray, blur_sigma: float) -> tuple[np.ndarray, np.ndarray]:
    """dI/du, dI/dv: 3x3 Gaussian blur then 3x3 Sobel / 8, replicated borders."""
    intensity = np.ascontiguousarray(intensity, dtype=np.float32)
    blurred = np.empty(intensity.shape, dtype=np.float64)
    dx = np.empty(intensity.shape, dtype=np.float32)
    dy = np.empty(intensity.shape, dtype=np.float32)
    _run(_blur_rows, intensity.size, intensity, gaussian3x3(blur_sigma), blurred)
    _run(_sobel_rows, intensity.size, blurred, SOBEL_X, SOBEL_Y, dx, dy)
    return dx, dy


def discontinuity_mask(depth: np.ndarray, window: int, jump: float, max_bad: int) -> np.ndarray:
    """True where colour may be fused (paper VI-B's 7x7 check; see the reference)."""
    depth = np.ascontiguousarray(depth, dtype=np.float32)
    out = np.empty(depth.shape, dtype=np.bool_)
    _run(
        _discontinuity_rows,
        depth.size,
        depth,
        int(window) // 2,
        np.float32(jump),
        int(max_bad),
        out,
    )
    return out


def preprocess_frame(
    colour: np.ndarray, depth: np.ndarray, camera: Intrinsics, config: PreprocessConfig
) -> PreprocessedFrame:
    """Everything tracking and fusion need from one RGB-D pair (kintinuous_ref.preprocess)."""
    check_frame_inputs(colour, depth, camera)
    import kintinuous_fast.preprocess.cpu as stages

    return preprocess_frame_with(stages, colour, depth, camera, config)
