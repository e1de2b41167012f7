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
from typing import Any

import numpy as np
from numba import cuda

from kintinuous_fast.preprocess.host import (
    SOBEL_X,
    SOBEL_Y,
    gaussian3x3,
    inverse_two_variance,
    preprocess_frame_with,
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
    to_device,
)
from kintinuous_fast.targets.cuda_graphs import segment
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
    the fast stages")."""
    if not is_device(vertices):
        return host_model_pyramid(vertices, normals, levels)
    pyramid = [(vertices, normals)]
    for _ in range(1, levels):
        finer_vertices, finer_normals = pyramid[-1]
        pyramid.append((_every_other_pixel(finer_vertices), _every_other_pixel(finer_normals)))
    return pyramid


def _every_other_pixel(source: Any) -> Any:
    height, width = source.shape[0] // 2, source.shape[1] // 2
    out = pooled_array("preprocess", (height, width, source.shape[2]), dtype=source.dtype)
    _launch(_subsample_kernel, (height, width), source, out)
    return out


def metric_depth(depth: Any, max_depth: float, depth_scale: float = 5000.0) -> Any:
    """float32 metres, 0 where NaN, <= 0 or farther than max_depth (integers: raw units)."""
    integer = bool(np.issubdtype(depth.dtype, np.integer))
    raw = to_device(depth, None if integer else np.float32)
    out = pooled_array("preprocess", depth.shape, dtype=np.float32)
    _launch(
        _metric_depth_kernel,
        depth.shape,
        raw,
        integer,
        np.float32(depth_scale),
        np.float32(max_depth),
        out,
    )
    return like_input(out, depth)


def bilateral_filter(depth: Any, sigma_space: float, sigma_depth: float, radius: int) -> Any:
    """Edge-preserving smoothing of a depth map; holes stay holes (see the reference)."""
    d_depth = to_device(depth, np.float32)
    out = pooled_array("preprocess", depth.shape, dtype=np.float32)
    spatial = _spatial_table(float(sigma_space), int(radius))
    inv_two_sigma2 = inverse_two_variance(sigma_depth)
    _launch(_bilateral_kernel, depth.shape, d_depth, spatial, int(radius), inv_two_sigma2, out)
    return like_input(out, depth)


def pyramid_down_depth(depth: Any, cutoff: float) -> Any:
    """Half-size depth by the edge-aware 5x5 Gaussian centred on each even pixel."""
    shape = (depth.shape[0] // 2, depth.shape[1] // 2)
    out = pooled_array("preprocess", shape, dtype=np.float32)
    _launch(_pyrdown_depth_kernel, shape, to_device(depth, np.float32), float(cutoff), out)
    return like_input(out, depth)


def pyramid_down_intensity(image: Any) -> Any:
    """Half-size image by the 5x5 Gaussian, weights renormalised at the border."""
    shape = (image.shape[0] // 2, image.shape[1] // 2)
    out = pooled_array("preprocess", shape, dtype=np.float32)
    _launch(_pyrdown_intensity_kernel, shape, to_device(image, np.float32), out)
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
    shape = intensity.shape
    blurred = pooled_array("preprocess", shape, dtype=np.float64)
    dx = pooled_array("preprocess", shape, dtype=np.float32)
    dy = pooled_array("preprocess", shape, dtype=np.float32)
    gaussian = _gaussian_table(float(blur_sigma))
    _launch(_correlate_kernel, shape, to_device(intensity, np.float32), gaussian, blurred)
    _launch(_sobel_kernel, shape, blurred, *_sobel_tables(), dx, dy)
    return like_input(dx, intensity), like_input(dy, intensity)


def discontinuity_mask(depth: Any, window: int, jump: float, max_bad: int) -> Any:
    """True where colour may be fused (paper VI-B's 7x7 check; see the reference)."""
    out = pooled_array("preprocess", depth.shape, dtype=np.bool_)
    _launch(
        _discontinuity_kernel,
        depth.shape,
        to_device(depth, np.float32),
        int(window) // 2,
        np.float32(jump),
        int(max_bad),
        out,
    )
    return like_input(out, depth)


@segment
def preprocess_frame(
    colour: Any, depth: Any, camera: Intrinsics, config: PreprocessConfig
) -> PreprocessedFrame:
    """Everything tracking and fusion need from one RGB-D pair (kintinuous_ref.preprocess).

    Host images in: one upload, every stage on the device, the frame copied back at the end.
    Device images in: a frame of device arrays (nothing crosses to the host)."""
    check_frame_inputs(colour, depth, camera)
    import kintinuous_fast.preprocess.cuda as stages

    on_device = is_device(depth)
    frame = preprocess_frame_with(stages, to_device(colour), to_device(depth), camera, config)
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
