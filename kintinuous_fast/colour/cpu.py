# ruff: noqa: ANN001, ANN201  (numba loops: argument types come from the call)
"""kintinuous_ref.colour's colour_weights on the CPU: one loop over rows (run on all threads) around
kintinuous_fast.tsdf.ops.colour_weight, in place of the reference's three whole-image NumPy
passes (docs/benchmarks.md, "Numbers behind the fast stages"). Bit-identical. angle_weight is
the reference's.
"""

from __future__ import annotations

import numpy as np

from kintinuous_fast.targets import cpu_jit_numpy_errors
from kintinuous_fast.targets.cache import register_slowest
from kintinuous_fast.targets.cpu import claimed_items, parallel_part, run_parallel
from kintinuous_fast.tsdf.ops import build_colour_weight
from kintinuous_ref.colour import angle_weight
from kintinuous_ref.config import ColourConfig
from kintinuous_ref.preprocess import PreprocessedFrame

__all__ = ["angle_weight", "colour_weights"]

colour_weight = build_colour_weight(cpu_jit_numpy_errors).colour_weight


@register_slowest("colour")
@parallel_part(error_model="numpy")
def _weights_loop(claims, parts, depth, mask, normals, use_mask, use_angle, out):
    for v in claimed_items(claims, depth.shape[0], parts):
        for u in range(depth.shape[1]):
            nz = normals[v, u, 2]
            out[v, u] = colour_weight(depth[v, u], mask[v, u], nz, use_mask, use_angle)


def colour_weights(frame: PreprocessedFrame, config: ColourConfig) -> np.ndarray:
    """Weight (H, W) float32 of each pixel's colour update; 0 = do not update (paper VI-B)."""
    depth = np.ascontiguousarray(frame.depth, dtype=np.float32)
    out = np.empty(depth.shape, dtype=np.float32)
    run_parallel(
        _weights_loop,
        depth,
        np.asarray(frame.colour_mask, dtype=np.bool_),
        np.asarray(frame.levels[0].normals, dtype=np.float32),
        bool(config.discontinuity_check),
        bool(config.angle_weighting),
        out,
    )
    return out
