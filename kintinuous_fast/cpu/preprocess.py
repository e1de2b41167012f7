# ruff: noqa: ANN001, ANN201  (numba kernels and loops: argument types come from the call)
"""kintinuous_ref.preprocess on the CPU: one prange loop per stage around kintinuous_fast.ops.

Same names, signatures and results as the reference (see tests/test_fast_preprocess.py for the
stated tolerances); arrays are NumPy arrays.
"""

from __future__ import annotations

import numba
import numpy as np
from numba import prange

from kintinuous_fast._host import (
    SOBEL_X,
    SOBEL_Y,
    check_frame_inputs,
    gaussian3x3,
    preprocess_frame_with,
    spatial_weights,
)
from kintinuous_fast.ops import cpu_jit
from kintinuous_fast.ops.preprocess import build_ops
from kintinuous_ref.camera import Intrinsics
from kintinuous_ref.config import PreprocessConfig
from kintinuous_ref.preprocess import PreprocessedFrame, PyramidLevel, model_pyramid

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

_ops = build_ops(cpu_jit)
# Module-level names: numba resolves the scalar functions as globals of the loops below.
metric_value = _ops.metric_value
bilateral_pixel = _ops.bilateral_pixel
pyrdown_depth_pixel = _ops.pyrdown_depth_pixel
pyrdown_intensity_pixel = _ops.pyrdown_intensity_pixel
vertex_pixel = _ops.vertex_pixel
normal_pixel = _ops.normal_pixel
intensity_pixel = _ops.intensity_pixel
correlate3x3_pixel = _ops.correlate3x3_pixel
discontinuity_pixel = _ops.discontinuity_pixel

_loop = numba.njit(parallel=True, cache=True)


@_loop
def _metric_depth_loop(raw, integer, depth_scale, max_depth, out):
    for v in prange(raw.shape[0]):
        for u in range(raw.shape[1]):
            out[v, u] = metric_value(raw[v, u], integer, depth_scale, max_depth)


@_loop
def _bilateral_loop(depth, spatial, radius, two_sigma_d2, out):
    for v in prange(depth.shape[0]):
        for u in range(depth.shape[1]):
            out[v, u] = bilateral_pixel(depth, v, u, spatial, radius, two_sigma_d2)


@_loop
def _pyrdown_depth_loop(depth, cutoff, out):
    for v in prange(out.shape[0]):
        for u in range(out.shape[1]):
            out[v, u] = pyrdown_depth_pixel(depth, v, u, cutoff)


@_loop
def _pyrdown_intensity_loop(image, out):
    for v in prange(out.shape[0]):
        for u in range(out.shape[1]):
            out[v, u] = pyrdown_intensity_pixel(image, v, u)


@_loop
def _vertex_loop(depth, fx, fy, cx, cy, out):
    for v in prange(depth.shape[0]):
        for u in range(depth.shape[1]):
            out[v, u, 0], out[v, u, 1], out[v, u, 2] = vertex_pixel(depth, v, u, fx, fy, cx, cy)


@_loop
def _normal_loop(vertices, out):
    for v in prange(vertices.shape[0]):
        for u in range(vertices.shape[1]):
            out[v, u, 0], out[v, u, 1], out[v, u, 2] = normal_pixel(vertices, v, u)


@_loop
def _intensity_loop(colour, out):
    for v in prange(colour.shape[0]):
        for u in range(colour.shape[1]):
            out[v, u] = intensity_pixel(colour[v, u, 0], colour[v, u, 1], colour[v, u, 2])


@_loop
def _gradient_loop(intensity, blur, sobel_x, sobel_y, blurred, dx, dy):
    # Two passes over the image: the float64 blur first (as the reference), then both Sobels.
    for v in prange(intensity.shape[0]):
        for u in range(intensity.shape[1]):
            blurred[v, u] = correlate3x3_pixel(intensity, v, u, blur)
    for v in prange(intensity.shape[0]):
        for u in range(intensity.shape[1]):
            dx[v, u] = correlate3x3_pixel(blurred, v, u, sobel_x)
            dy[v, u] = correlate3x3_pixel(blurred, v, u, sobel_y)


@_loop
def _discontinuity_loop(depth, radius, jump, max_bad, out):
    for v in prange(depth.shape[0]):
        for u in range(depth.shape[1]):
            out[v, u] = discontinuity_pixel(depth, v, u, radius, jump, max_bad)


# ----------------------------------------------------------------------------------------------
# Public functions: kintinuous_ref.preprocess's signatures


def metric_depth(depth: np.ndarray, max_depth: float, depth_scale: float = 5000.0) -> np.ndarray:
    """float32 metres, 0 where NaN, <= 0 or farther than max_depth (integers: raw units)."""
    depth = np.ascontiguousarray(depth)
    integer = bool(np.issubdtype(depth.dtype, np.integer))
    if not integer and depth.dtype != np.float32:
        depth = depth.astype(np.float32)  # the reference's cast, before any comparison
    out = np.empty(depth.shape, dtype=np.float32)
    _metric_depth_loop(depth, integer, np.float32(depth_scale), np.float32(max_depth), out)
    return out


def bilateral_filter(
    depth: np.ndarray, sigma_space: float, sigma_depth: float, radius: int
) -> np.ndarray:
    """Edge-preserving smoothing of a depth map; holes stay holes (see the reference)."""
    depth = np.ascontiguousarray(depth, dtype=np.float32)
    out = np.empty(depth.shape, dtype=np.float32)
    spatial = spatial_weights(sigma_space, radius)
    _bilateral_loop(depth, spatial, int(radius), 2.0 * sigma_depth**2, out)
    return out


def pyramid_down_depth(depth: np.ndarray, cutoff: float) -> np.ndarray:
    """Half-size depth by the edge-aware 5x5 Gaussian centred on each even pixel."""
    depth = np.ascontiguousarray(depth, dtype=np.float32)
    out = np.empty((depth.shape[0] // 2, depth.shape[1] // 2), dtype=np.float32)
    _pyrdown_depth_loop(depth, float(cutoff), out)
    return out


def pyramid_down_intensity(image: np.ndarray) -> np.ndarray:
    """Half-size image by the 5x5 Gaussian, weights renormalised at the border."""
    image = np.ascontiguousarray(image, dtype=np.float32)
    out = np.empty((image.shape[0] // 2, image.shape[1] // 2), dtype=np.float32)
    _pyrdown_intensity_loop(image, out)
    return out


def vertex_map(depth: np.ndarray, camera: Intrinsics) -> np.ndarray:
    """Camera-frame points D K^-1 [u, v, 1]; NaN where D <= 0."""
    depth = np.ascontiguousarray(depth, dtype=np.float32)
    out = np.empty((*depth.shape, 3), dtype=np.float32)
    _vertex_loop(depth, float(camera.fx), float(camera.fy), float(camera.cx), float(camera.cy), out)
    return out


def normal_map(vertices: np.ndarray) -> np.ndarray:
    """Unit normals from neighbour differences, pointing to the camera; NaN where undefined."""
    vertices = np.ascontiguousarray(vertices, dtype=np.float32)
    out = np.empty(vertices.shape, dtype=np.float32)
    _normal_loop(vertices, out)
    return out


def intensity_image(colour: np.ndarray) -> np.ndarray:
    """I = 0.299 R + 0.587 G + 0.114 B, float32 in 0..255."""
    colour = np.ascontiguousarray(colour)
    out = np.empty(colour.shape[:2], dtype=np.float32)
    _intensity_loop(colour, out)
    return out


def intensity_gradients(intensity: np.ndarray, blur_sigma: float) -> tuple[np.ndarray, np.ndarray]:
    """dI/du, dI/dv: 3x3 Gaussian blur then 3x3 Sobel / 8, replicated borders."""
    intensity = np.ascontiguousarray(intensity, dtype=np.float32)
    blurred = np.empty(intensity.shape, dtype=np.float64)
    dx = np.empty(intensity.shape, dtype=np.float32)
    dy = np.empty(intensity.shape, dtype=np.float32)
    _gradient_loop(intensity, gaussian3x3(blur_sigma), SOBEL_X, SOBEL_Y, blurred, dx, dy)
    return dx, dy


def discontinuity_mask(depth: np.ndarray, window: int, jump: float, max_bad: int) -> np.ndarray:
    """True where colour may be fused (paper VI-B's 7x7 check; see the reference)."""
    depth = np.ascontiguousarray(depth, dtype=np.float32)
    out = np.empty(depth.shape, dtype=np.bool_)
    _discontinuity_loop(depth, int(window) // 2, np.float32(jump), int(max_bad), out)
    return out


def preprocess_frame(
    colour: np.ndarray, depth: np.ndarray, camera: Intrinsics, config: PreprocessConfig
) -> PreprocessedFrame:
    """Everything tracking and fusion need from one RGB-D pair (kintinuous_ref.preprocess)."""
    check_frame_inputs(colour, depth, camera)
    import kintinuous_fast.cpu.preprocess as stages

    return preprocess_frame_with(stages, colour, depth, camera, config)
