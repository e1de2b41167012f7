# ruff: noqa: ANN001, ANN201  (numba kernels: argument types come from the call)
"""kintinuous_ref.colour's colour_weights as one CUDA kernel, so that a frame on the device gets
its colour weights there (paper VI-B): per pixel, 1 where there is depth, times the
discontinuity mask when config.discontinuity_check, times |n_z| of the full-resolution normal
(0 where not finite) when config.angle_weighting. The float32 products of the reference's
factors: bit-identical weights. Arrays stay where they are given (kintinuous_fast.cuda).
"""

from __future__ import annotations

import math

import numpy as np
from numba import cuda

from kintinuous_fast.cuda import BLOCK_2D, grid_2d, like_input, to_device
from kintinuous_ref.config import ColourConfig
from kintinuous_ref.preprocess import PreprocessedFrame

__all__ = ["colour_weights"]


@cuda.jit
def _weights_kernel(depth, mask, normals, use_mask, use_angle, out):
    u, v = cuda.grid(2)
    if v < out.shape[0] and u < out.shape[1]:
        weight = np.float32(1.0) if depth[v, u] > 0 else np.float32(0.0)
        if use_mask and not mask[v, u]:
            weight = np.float32(0.0)
        if use_angle:
            nz = abs(normals[v, u, 2])
            weight *= nz if math.isfinite(nz) else np.float32(0.0)
        out[v, u] = weight


def colour_weights(frame: PreprocessedFrame, config: ColourConfig):
    """Weight (H, W) float32 of each pixel's colour update; 0 = do not update (paper VI-B)."""
    depth = to_device(frame.depth, np.float32)
    out = cuda.device_array(depth.shape, dtype=np.float32)
    _weights_kernel[grid_2d(*depth.shape), BLOCK_2D](
        depth,
        to_device(frame.colour_mask, np.bool_),
        to_device(frame.levels[0].normals, np.float32),
        bool(config.discontinuity_check),
        bool(config.angle_weighting),
        out,
    )
    return like_input(out, frame.depth)
