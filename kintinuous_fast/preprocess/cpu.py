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
(preprocess.cpu_bilateral), with ops.py's float32 weights.
"""

from __future__ import annotations

from types import SimpleNamespace

import numba
import numpy as np

from kintinuous_fast.preprocess.cpu_bilateral import PARALLEL_MIN, bilateral_filter
from kintinuous_fast.preprocess.host import SOBEL_X, SOBEL_Y, gaussian3x3, preprocess_frame_with
from kintinuous_fast.preprocess.ops import (
    build_discontinuity,
    build_intensity,
    build_metric_depth,
    build_pyramid,
    build_vertices_and_normals,
)
from kintinuous_fast.targets import pinhole
from kintinuous_fast.targets.cpu import claimed_items, parallel_part, run_parallel_above
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
    "check_frame_inputs",
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

# The ops are inlined into the row loops at numba IR level: as calls, they cost a frame about a
# millisecond more (docs/benchmarks.md, "Numbers behind the fast stages").
_ops = SimpleNamespace(
    **vars(build_metric_depth(_inline)),
    **vars(build_pyramid(_inline)),
    **vars(build_vertices_and_normals(_inline)),
    **vars(build_intensity(_inline)),
    **vars(build_discontinuity(_inline)),
)
# Module-level names: numba resolves the scalar functions as globals of the loops below.
metric_value = _ops.metric_value
binomial5 = _ops.binomial5
depth_tap_counts = _ops.depth_tap_counts
pyrdown_depth_result = _ops.pyrdown_depth_result
vertex_from_depth = _ops.vertex_from_depth
normal_from_edges = _ops.normal_from_edges
intensity_pixel = _ops.intensity_pixel
correlate3x3_pixel = _ops.correlate3x3_pixel
is_depth_jump = _ops.is_depth_jump
colour_fusable = _ops.colour_fusable


def _run(loop, pixels: int, *args) -> None:
    """run_parallel a loop, on the calling thread alone below PARALLEL_MIN pixels."""
    run_parallel_above(PARALLEL_MIN, loop, pixels, *args)


# ----------------------------------------------------------------------------------------------
# Row kernels (one output row; slices start at the first pixel so every index is >= 0)


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
