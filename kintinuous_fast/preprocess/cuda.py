# ruff: noqa: ANN001, ANN201  (numba kernels and loops: argument types come from the call)
"""kintinuous_ref.preprocess as CUDA kernels: one thread per output pixel around
each stage's ops.py (the same scalar functions the CPU backend loops over).

Same names, signatures and results as the reference (tests/test_fast_preprocess.py states the
tolerances). Arrays come back where they were given (kintinuous_fast.targets.cuda); preprocess_frame
uploads the images once and keeps every intermediate on the device. The weight tables go up once
per parameter set and stay there (numba's copy to the device waits for the device to finish the
work queued before it, so an upload per frame would also stall the host).
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from numba import cuda

from kintinuous_fast.preprocess.host import (
    SOBEL_X,
    SOBEL_Y,
    gaussian3x3,
    inverse_two_variance,
    spatial_exponents,
)
from kintinuous_fast.preprocess.ops import build_ops
from kintinuous_fast.targets import cuda_device_jit, is_device, pinhole, to_host
from kintinuous_fast.targets.cuda import (
    BLOCK_2D,
    grid_2d,
    kernel,
    like_input,
    pooled_array,
    pooled_arrays,
    to_device,
)
from kintinuous_fast.targets.cuda_graphs import segment, signed
from kintinuous_ref.camera import Intrinsics
from kintinuous_ref.config import PreprocessConfig
from kintinuous_ref.preprocess import PreprocessedFrame, PyramidLevel, check_frame_inputs
from kintinuous_ref.preprocess import model_pyramid as host_model_pyramid

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


@cuda.jit(device=True)
def _power_of_two_neg(n):
    """2^-n as float32 (int(): the simulator's math.ldexp takes Python integers only)."""
    return math.ldexp(np.float32(1.0), int(-n))


_ops = build_ops(cuda_device_jit(), cuda_device_jit(), _power_of_two_neg)
metric_value = _ops.metric_value
bilateral_pixel = _ops.bilateral_pixel
pyrdown_depth_pixel = _ops.pyrdown_depth_pixel
pyrdown_intensity_pixel = _ops.pyrdown_intensity_pixel
vertex_pixel = _ops.vertex_pixel
normal_pixel = _ops.normal_pixel
intensity_pixel = _ops.intensity_pixel
correlate3x3_pixel = _ops.correlate3x3_pixel
discontinuity_pixel = _ops.discontinuity_pixel


@kernel
def _metric_depth_kernel(raw, integer, depth_scale, max_depth, out):
    u, v = cuda.grid(2)
    if v < out.shape[0] and u < out.shape[1]:
        out[v, u] = metric_value(raw[v, u], integer, depth_scale, max_depth)


@kernel
def _bilateral_kernel(depth, spatial, radius, inv_two_sigma2, out):
    u, v = cuda.grid(2)
    if v < out.shape[0] and u < out.shape[1]:
        out[v, u] = bilateral_pixel(depth, v, u, spatial, radius, inv_two_sigma2)


@kernel
def _pyrdown_depth_kernel(depth, cutoff, out):
    u, v = cuda.grid(2)
    if v < out.shape[0] and u < out.shape[1]:
        out[v, u] = pyrdown_depth_pixel(depth, v, u, cutoff)


@kernel
def _pyrdown_intensity_kernel(image, out):
    u, v = cuda.grid(2)
    if v < out.shape[0] and u < out.shape[1]:
        out[v, u] = pyrdown_intensity_pixel(image, v, u)


@kernel
def _vertex_kernel(depth, camera, out):
    u, v = cuda.grid(2)
    if v < out.shape[0] and u < out.shape[1]:
        out[v, u, 0], out[v, u, 1], out[v, u, 2] = vertex_pixel(depth, v, u, camera)


@kernel
def _normal_kernel(vertices, out):
    u, v = cuda.grid(2)
    if v < out.shape[0] and u < out.shape[1]:
        out[v, u, 0], out[v, u, 1], out[v, u, 2] = normal_pixel(vertices, v, u)


@kernel
def _intensity_kernel(colour, out):
    u, v = cuda.grid(2)
    if v < out.shape[0] and u < out.shape[1]:
        out[v, u] = intensity_pixel(colour[v, u, 0], colour[v, u, 1], colour[v, u, 2])


@kernel
def _correlate_kernel(image, kernel, out):
    u, v = cuda.grid(2)
    if v < out.shape[0] and u < out.shape[1]:
        out[v, u] = correlate3x3_pixel(image, v, u, kernel)


@kernel
def _sobel_kernel(blurred, sobel_x, sobel_y, dx, dy):
    u, v = cuda.grid(2)
    if v < dx.shape[0] and u < dx.shape[1]:
        dx[v, u] = correlate3x3_pixel(blurred, v, u, sobel_x)
        dy[v, u] = correlate3x3_pixel(blurred, v, u, sobel_y)


@kernel
def _discontinuity_kernel(depth, radius, jump, max_bad, out):
    u, v = cuda.grid(2)
    if v < out.shape[0] and u < out.shape[1]:
        out[v, u] = discontinuity_pixel(depth, v, u, radius, jump, max_bad)


@kernel
def _subsample_kernel(source, out):
    u, v = cuda.grid(2)
    if v < out.shape[0] and u < out.shape[1]:
        for channel in range(out.shape[2]):
            out[v, u, channel] = source[2 * v, 2 * u, channel]


def _launch(compiled: Any, shape: tuple[int, ...], *args: Any) -> None:
    compiled[grid_2d(shape[0], shape[1]), BLOCK_2D](*args)


# ----------------------------------------------------------------------------------------------
# Constant tables, on the device for the run: kernels only read them


@functools.lru_cache(maxsize=16)
def _spatial_table(sigma_space: float, radius: int) -> Any:
    """spatial_exponents(sigma_space, radius) on the device, uploaded on first use."""
    return cuda.to_device(spatial_exponents(sigma_space, radius))


@functools.lru_cache(maxsize=16)
def _gaussian_table(blur_sigma: float) -> Any:
    """gaussian3x3(blur_sigma) on the device, uploaded on first use."""
    return cuda.to_device(gaussian3x3(blur_sigma))


@functools.lru_cache(maxsize=1)
def _sobel_tables() -> tuple[Any, Any]:
    """SOBEL_X and SOBEL_Y on the device, uploaded on first use."""
    return cuda.to_device(SOBEL_X), cuda.to_device(SOBEL_Y)


# ----------------------------------------------------------------------------------------------
# Public functions: kintinuous_ref.preprocess's signatures


def model_pyramid(vertices: Any, normals: Any, levels: int) -> list[tuple[Any, Any]]:
    """The reference's pixel (2u, 2v) pyramid of raycast maps; device maps stay on the device.

    Each coarser level is copied by a kernel into a contiguous array rather than taken as a
    strided view: numba builds a view of a device array with a Python loop over its elements,
    which costs about half a second a frame at 640x480 (docs/benchmarks.md, "Numbers behind
    the fast stages"). The copies are a signed segment (targets.cuda_graphs.signed) of the
    maps, the finest given and the coarser ones pooled."""
    if not is_device(vertices):
        return host_model_pyramid(vertices, normals, levels)
    pyramid = [(vertices, normals)]
    for _ in range(1, levels):
        pyramid.append(tuple(_half_map(finer) for finer in pyramid[-1]))
    maps = tuple(pyramid)
    signed("model pyramid", maps, lambda: _subsample_pyramid(maps))
    return pyramid


def _half_map(finer: Any) -> Any:
    """A pooled map of half `finer`'s size."""
    shape = (finer.shape[0] // 2, finer.shape[1] // 2, finer.shape[2])
    return pooled_array("preprocess", shape, dtype=finer.dtype)


def _subsample_pyramid(pyramid: tuple) -> None:
    """Each coarser level's two maps from the finer level's pixels (2u, 2v)."""
    for finer, coarser in zip(pyramid, pyramid[1:], strict=False):
        for source, out in zip(finer, coarser, strict=True):
            _launch(_subsample_kernel, out.shape, source, out)


def metric_depth(depth: Any, max_depth: float, depth_scale: float = 5000.0) -> Any:
    """float32 metres, 0 where NaN, <= 0 or farther than max_depth (integers: raw units)."""
    out = pooled_array("preprocess", depth.shape, dtype=np.float32)
    _metric_depth_into(out, _raw_depth(depth), float(max_depth), float(depth_scale))
    return like_input(out, depth)


def bilateral_filter(depth: Any, sigma_space: float, sigma_depth: float, radius: int) -> Any:
    """Edge-preserving smoothing of a depth map; holes stay holes (see the reference)."""
    out = pooled_array("preprocess", depth.shape, dtype=np.float32)
    weights = _bilateral_weights(sigma_space, sigma_depth, radius)
    _bilateral_into(out, to_device(depth, np.float32), weights)
    return like_input(out, depth)


def pyramid_down_depth(depth: Any, cutoff: float) -> Any:
    """Half-size depth by the edge-aware 5x5 Gaussian centred on each even pixel."""
    out = pooled_array("preprocess", _half(depth.shape), dtype=np.float32)
    _launch(_pyrdown_depth_kernel, out.shape, to_device(depth, np.float32), float(cutoff), out)
    return like_input(out, depth)


def pyramid_down_intensity(image: Any) -> Any:
    """Half-size image by the 5x5 Gaussian, weights renormalised at the border."""
    out = pooled_array("preprocess", _half(image.shape), dtype=np.float32)
    _launch(_pyrdown_intensity_kernel, out.shape, to_device(image, np.float32), out)
    return like_input(out, image)


def vertex_map(depth: Any, camera: Intrinsics) -> Any:
    """Camera-frame points D K^-1 [u, v, 1]; NaN where D <= 0."""
    out = pooled_array("preprocess", (*depth.shape, 3), dtype=np.float32)
    _launch(_vertex_kernel, depth.shape, to_device(depth, np.float32), pinhole(camera), out)
    return like_input(out, depth)


def normal_map(vertices: Any) -> Any:
    """Unit normals from neighbour differences, pointing to the camera; NaN where undefined."""
    out = pooled_array("preprocess", vertices.shape, dtype=np.float32)
    _launch(_normal_kernel, vertices.shape, to_device(vertices, np.float32), out)
    return like_input(out, vertices)


def intensity_image(colour: Any) -> Any:
    """I = 0.299 R + 0.587 G + 0.114 B, float32 in 0..255."""
    out = pooled_array("preprocess", colour.shape[:2], dtype=np.float32)
    _launch(_intensity_kernel, colour.shape, to_device(colour), out)
    return like_input(out, colour)


def intensity_gradients(intensity: Any, blur_sigma: float) -> tuple[Any, Any]:
    """dI/du, dI/dv: 3x3 Gaussian blur then 3x3 Sobel / 8, replicated borders."""
    blurred, dx, dy = _gradient_buffers(intensity.shape)
    tables = _gradient_tables(blur_sigma)
    _gradients_into(blurred, dx, dy, to_device(intensity, np.float32), tables)
    return like_input(dx, intensity), like_input(dy, intensity)


def discontinuity_mask(depth: Any, window: int, jump: float, max_bad: int) -> Any:
    """True where colour may be fused (paper VI-B's 7x7 check; see the reference)."""
    out = pooled_array("preprocess", depth.shape, dtype=np.bool_)
    rule = _discontinuity_rule(window, jump, max_bad)
    _launch(_discontinuity_kernel, depth.shape, to_device(depth, np.float32), *rule, out)
    return like_input(out, depth)


# ----------------------------------------------------------------------------------------------
# The launches behind the public functions, into given device buffers: the stages call them one
# by one, a frame (preprocess_frame) calls them all into one set of buffers


def _half(shape: tuple[int, ...]) -> tuple[int, int]:
    return shape[0] // 2, shape[1] // 2


def _raw_depth(depth: Any) -> Any:
    """The depth image on the device as the metric kernel reads it: integers as they are."""
    return to_device(depth, None if np.issubdtype(depth.dtype, np.integer) else np.float32)


def _metric_depth_into(out: Any, raw: Any, max_depth: float, depth_scale: float) -> None:
    integer = bool(np.issubdtype(raw.dtype, np.integer))
    scale, limit = np.float32(depth_scale), np.float32(max_depth)
    _launch(_metric_depth_kernel, out.shape, raw, integer, scale, limit, out)


def _bilateral_weights(sigma_space: float, sigma_depth: float, radius: int) -> tuple:
    """(spatial table on the device, radius, 1 / 2 sigma_d^2): the bilateral kernel's weights."""
    spatial = _spatial_table(float(sigma_space), int(radius))
    return spatial, int(radius), inverse_two_variance(sigma_depth)


def _bilateral_into(out: Any, depth: Any, weights: tuple) -> None:
    _launch(_bilateral_kernel, out.shape, depth, *weights, out)


def _gradient_buffers(shape: tuple[int, ...]) -> tuple[Any, Any, Any]:
    """(blurred float64, dx, dy) for intensity_gradients at `shape`."""
    blurred = pooled_array("preprocess", shape, dtype=np.float64)
    dx = pooled_array("preprocess", shape, dtype=np.float32)
    dy = pooled_array("preprocess", shape, dtype=np.float32)
    return blurred, dx, dy


def _gradient_tables(blur_sigma: float) -> tuple[Any, Any, Any]:
    """(Gaussian, Sobel x, Sobel y) on the device."""
    return (_gaussian_table(float(blur_sigma)), *_sobel_tables())


def _gradients_into(blurred: Any, dx: Any, dy: Any, intensity: Any, tables: tuple) -> None:
    gaussian, sobel_x, sobel_y = tables
    _launch(_correlate_kernel, dx.shape, intensity, gaussian, blurred)
    _launch(_sobel_kernel, dx.shape, blurred, sobel_x, sobel_y, dx, dy)


def _discontinuity_rule(window: int, jump: float, max_bad: int) -> tuple[int, np.float32, int]:
    return int(window) // 2, np.float32(jump), int(max_bad)


# ----------------------------------------------------------------------------------------------
# A whole frame


@dataclass
class _FrameBuffers:
    """Every device array one frame's preprocessing writes, per pyramid level: the metric depth
    (`raw`), the filtered depth, the intensity, the maps, the gradients and the blur before
    them; and the colour mask of the finest level."""

    raw: list[Any]
    filtered: list[Any]
    intensity: list[Any]
    vertices: list[Any]
    normals: list[Any]
    gradients: list[tuple[Any, Any, Any]]  # (blurred, dx, dy)
    mask: Any

    @classmethod
    def pooled(cls, shape: tuple[int, int], levels: int) -> _FrameBuffers:
        """A set from the pool (targets.cuda.pooled_arrays): one whose arrays are all free."""
        sizes = [(shape[0] >> level, shape[1] >> level) for level in range(levels)]
        float32, float64 = np.dtype(np.float32).str, np.dtype(np.float64).str
        images = [(size, float32) for size in sizes]
        maps = [((*size, 3), float32) for size in sizes]
        blurs = [(size, float64) for size in sizes]
        mask = (sizes[0], np.dtype(np.bool_).str)
        specs = (*images, *images, *images, *maps, *maps, *blurs, *images, *images, mask)
        arrays = pooled_arrays("frame", specs)
        raw, filtered, intensity, vertices, normals, blurred, dx, dy = (
            list(arrays[part * levels : (part + 1) * levels]) for part in range(8)
        )
        gradients = list(zip(blurred, dx, dy, strict=True))
        return cls(raw, filtered, intensity, vertices, normals, gradients, arrays[-1])

    def arrays(self) -> tuple:
        return (
            *self.raw, *self.filtered, *self.intensity, *self.vertices, *self.normals,
            *(array for level in self.gradients for array in level), self.mask,
        )  # fmt: skip


@functools.lru_cache(maxsize=16)
def _level_cameras(camera: Intrinsics, levels: int) -> tuple[Intrinsics, ...]:
    return tuple(camera.at_level(level) for level in range(levels))


@functools.lru_cache(maxsize=16)
def _frame_settings(camera: Intrinsics, config: PreprocessConfig) -> tuple:
    """What the frame's kernels take beyond images and buffers, each once: (metric depth's
    limit and scale, the bilateral weights, the pyramid's cutoff, the gradient tables, each
    level's pinhole, the discontinuity rule). Kept per camera and configuration."""
    return (
        (float(config.max_depth), float(camera.depth_scale)),
        _bilateral_weights(
            config.bilateral_sigma_space, config.bilateral_sigma_depth, config.bilateral_radius
        ),
        float(config.pyramid_depth_cutoff),
        _gradient_tables(config.gradient_blur_sigma),
        tuple(pinhole(level) for level in _level_cameras(camera, config.pyramid_levels)),
        _discontinuity_rule(
            config.discontinuity_window, config.discontinuity_jump, config.discontinuity_max_bad
        ),
    )


def _frame_into(buffers: _FrameBuffers, colour: Any, raw: Any, settings: tuple) -> None:
    """kintinuous_ref.preprocess.preprocess_frame's stages (kintinuous_fast.preprocess.host's
    order) into `buffers`: nothing but the arguments may vary these launches."""
    metric, weights, cutoff, tables, pinholes, rule = settings
    b = buffers
    _metric_depth_into(b.raw[0], raw, *metric)
    _bilateral_into(b.filtered[0], b.raw[0], weights)
    _launch(_intensity_kernel, colour.shape, colour, b.intensity[0])
    for level in range(len(b.raw)):
        if level > 0:
            _halve(_pyrdown_depth_kernel, b.raw, level, cutoff)
            _halve(_pyrdown_depth_kernel, b.filtered, level, cutoff)
            _halve(_pyrdown_intensity_kernel, b.intensity, level)
        depth, vertices = b.filtered[level], b.vertices[level]
        _launch(_vertex_kernel, depth.shape, depth, pinholes[level], vertices)
        _gradients_into(*b.gradients[level], b.intensity[level], tables)
        _launch(_normal_kernel, vertices.shape, vertices, b.normals[level])
    _launch(_discontinuity_kernel, b.mask.shape, b.raw[0], *rule, b.mask)


def _halve(compiled: Any, pyramid: list[Any], level: int, *arguments: Any) -> None:
    """pyramid[level] from pyramid[level - 1] by a pyramid-down kernel."""
    out = pyramid[level]
    _launch(compiled, out.shape, pyramid[level - 1], *arguments, out)


@segment
def preprocess_frame(
    colour: Any, depth: Any, camera: Intrinsics, config: PreprocessConfig
) -> PreprocessedFrame:
    """Everything tracking and fusion need from one RGB-D pair (kintinuous_ref.preprocess).

    Host images in: one upload, every stage on the device, the frame copied back at the end.
    Device images in: a frame of device arrays (nothing crosses to the host). The frame's
    launches are a signed segment (targets.cuda_graphs.signed) of its images, buffers and
    settings: with graphs on, a frame whose buffers repeat replays without this Python."""
    check_frame_inputs(colour, depth, camera)
    on_device = is_device(depth)
    colour_on_device, raw = to_device(colour), _raw_depth(depth)
    buffers = _FrameBuffers.pooled(tuple(depth.shape), config.pyramid_levels)
    settings = _frame_settings(camera, config)
    signed(
        "preprocess",
        (colour_on_device, raw, buffers.arrays(), settings),
        lambda: _frame_into(buffers, colour_on_device, raw, settings),
    )
    levels = [
        PyramidLevel(
            level_camera,
            buffers.raw[level],
            buffers.vertices[level],
            buffers.normals[level],
            buffers.intensity[level],
            *buffers.gradients[level][1:],
        )
        for level, level_camera in enumerate(_level_cameras(camera, config.pyramid_levels))
    ]
    frame = PreprocessedFrame(
        colour=colour_on_device, depth=levels[0].depth, levels=levels, colour_mask=buffers.mask
    )
    if on_device:
        return frame
    return frame_to_host(frame, colour)


def frame_to_host(frame: PreprocessedFrame, colour: np.ndarray | None = None) -> PreprocessedFrame:
    """A copy of a device-resident frame with NumPy arrays (the pipeline's explicit download)."""
    levels = [
        PyramidLevel(
            level.camera,
            to_host(level.depth),
            to_host(level.vertices),
            to_host(level.normals),
            to_host(level.intensity),
            to_host(level.intensity_dx),
            to_host(level.intensity_dy),
        )
        for level in frame.levels
    ]
    return PreprocessedFrame(
        colour=to_host(frame.colour) if colour is None else colour,
        depth=levels[0].depth,
        levels=levels,
        colour_mask=to_host(frame.colour_mask),
    )
