# ruff: noqa: ANN001, ANN201  (numba kernels: argument types come from the call)
"""kintinuous_ref.colour's colour_weights as one CUDA kernel around
kintinuous_fast.tsdf.ops.colour_weight, so that a frame on the device gets its colour weights
there (paper VI-B); bit-identical weights. Arrays stay where they are given
(kintinuous_fast.targets.cuda).
"""

from __future__ import annotations

import numpy as np
from numba import cuda

from kintinuous_fast.targets import cuda_device_jit
from kintinuous_fast.targets.cuda import (
    BLOCK_2D,
    grid_2d,
    kernel,
    like_input,
    pooled_array,
    to_device,
)
from kintinuous_fast.targets.cuda_graphs import segment, signed
from kintinuous_fast.tsdf.ops import build_colour_weight
from kintinuous_ref.colour import angle_weight
from kintinuous_ref.config import ColourConfig
from kintinuous_ref.preprocess import PreprocessedFrame

__all__ = ["angle_weight", "colour_weights"]

colour_weight = build_colour_weight(cuda_device_jit()).colour_weight


@kernel
def _weights_kernel(depth, mask, normals, use_mask, use_angle, out):
    u, v = cuda.grid(2)
    if v < out.shape[0] and u < out.shape[1]:
        out[v, u] = colour_weight(depth[v, u], mask[v, u], normals[v, u, 2], use_mask, use_angle)


@segment
def colour_weights(frame: PreprocessedFrame, config: ColourConfig):
    """Weight (H, W) float32 of each pixel's colour update; 0 = do not update (paper VI-B)."""
    depth = to_device(frame.depth, np.float32)
    out = pooled_array("colour weights", depth.shape, np.float32)
    weights = (
        depth,
        to_device(frame.colour_mask, np.bool_),
        to_device(frame.levels[0].normals, np.float32),
        bool(config.discontinuity_check),
        bool(config.angle_weighting),
        out,
    )
    signed("colour weights", weights, lambda: _launch_weights(weights))
    return like_input(out, frame.depth)


def _launch_weights(weights: tuple) -> None:
    """colour_weights' one launch (a signed segment: it replays without this Python)."""
    depth = weights[0]
    _weights_kernel[grid_2d(*depth.shape), BLOCK_2D](*weights)
