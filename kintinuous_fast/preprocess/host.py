"""Host-side code shared by the cpu and cuda backends: small weight tables (computed with the
same NumPy calls as the reference so that both see identical weights), input checks, and the
stage order of preprocess_frame, written once over "a module with the per-stage functions"."""

from __future__ import annotations

from types import ModuleType
from typing import Any

import numpy as np

from kintinuous_ref.camera import Intrinsics
from kintinuous_ref.config import PreprocessConfig
from kintinuous_ref.preprocess import PreprocessedFrame, PyramidLevel

# Sobel kernels scaled by 1/8: intensity change per pixel (as the reference).
SOBEL_X = np.array([[-1.0, 0.0, 1.0], [-2.0, 0.0, 2.0], [-1.0, 0.0, 1.0]]) / 8.0
SOBEL_Y = np.ascontiguousarray(SOBEL_X.T)


def gaussian3x3(sigma: float) -> np.ndarray:
    """The normalised 3x3 Gaussian of the reference's intensity_gradients (float64)."""
    g = np.exp(-(np.array([-1.0, 0.0, 1.0]) ** 2) / (2.0 * sigma**2))
    g /= g.sum()
    return np.outer(g, g)


def spatial_exponents(sigma_space: float, radius: int) -> np.ndarray:
    """(dx^2 + dy^2) / 2 sigma_s^2 per window offset, float32: the spatial part of the bilateral
    weights' exponent (ops.bilateral_weight)."""
    offsets = np.arange(-radius, radius + 1, dtype=np.float64) ** 2
    return ((offsets[:, None] + offsets[None, :]) / (2.0 * sigma_space**2)).astype(np.float32)


def inverse_two_variance(sigma_depth: float) -> np.float32:
    """1 / 2 sigma_d^2 in float32, the depth part of the bilateral weights' exponent."""
    return np.float32(1.0 / (2.0 * sigma_depth**2))


def preprocess_frame_with(
    stages: ModuleType,
    colour: Any,
    depth: Any,
    camera: Intrinsics,
    config: PreprocessConfig,
) -> PreprocessedFrame:
    """kintinuous_ref.preprocess.preprocess_frame's stage order, calling `stages`' functions
    (so the arrays stay wherever that backend keeps them)."""
    raw = stages.metric_depth(depth, config.max_depth, camera.depth_scale)
    filtered = stages.bilateral_filter(
        raw, config.bilateral_sigma_space, config.bilateral_sigma_depth, config.bilateral_radius
    )
    intensity = stages.intensity_image(colour)
    levels: list[PyramidLevel] = []
    for level in range(config.pyramid_levels):
        if level > 0:
            raw = stages.pyramid_down_depth(raw, config.pyramid_depth_cutoff)
            filtered = stages.pyramid_down_depth(filtered, config.pyramid_depth_cutoff)
            intensity = stages.pyramid_down_intensity(intensity)
        level_camera = camera.at_level(level)
        vertices = stages.vertex_map(filtered, level_camera)
        dx, dy = stages.intensity_gradients(intensity, config.gradient_blur_sigma)
        levels.append(
            PyramidLevel(
                level_camera, raw, vertices, stages.normal_map(vertices), intensity, dx, dy
            )
        )
    mask = stages.discontinuity_mask(
        levels[0].depth,
        config.discontinuity_window,
        config.discontinuity_jump,
        config.discontinuity_max_bad,
    )
    return PreprocessedFrame(colour=colour, depth=levels[0].depth, levels=levels, colour_mask=mask)
