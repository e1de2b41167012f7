"""Per-pixel maths of kintinuous_ref.preprocess, written once for the CPU and the CUDA target.

Every function computes ONE output pixel exactly as the reference computes the whole image (same
formula, same order of summation, same float32/float64 choices), so the backends agree with the
reference to the last bit or the last unit in the last place (exp and FMA contraction may differ).
Neighbours outside the image are skipped where the reference fills them with a value that does
not contribute (a weight times 0, or NaN in a comparison), which leaves every sum unchanged.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from types import SimpleNamespace
from typing import Any

import numpy as np


def build_ops(jit: Callable[[Any], Any]) -> SimpleNamespace:
    """The scalar functions of preprocessing compiled with `jit` (see kintinuous_fast.targets)."""

    @jit
    def metric_value(raw: Any, integer: bool, depth_scale: Any, max_depth: Any) -> Any:
        """float32 metres of one raw depth value, 0 where untrustworthy (ref metric_depth).
        `depth_scale` and `max_depth` are float32, as NumPy 2 casts Python floats there."""
        d = np.float32(raw)
        if integer:
            d = d / depth_scale
        if math.isfinite(d) and d > 0 and d <= max_depth:
            return d
        return np.float32(0.0)

    @jit
    def bilateral_pixel(
        depth: Any, v: int, u: int, spatial: Any, radius: int, two_sigma_d2: float
    ) -> float:
        """Bilateral mean at (v, u): spatial[dy, dx] * exp(-(D(p)-D(q))^2 / 2 sigma_d^2)."""
        height, width = depth.shape
        centre = float(depth[v, u])
        if not centre > 0.0:
            return 0.0
        total = 0.0
        weights = 0.0
        for dy in range(-radius, radius + 1):
            y = v + dy
            if y < 0 or y >= height:
                continue
            for dx in range(-radius, radius + 1):
                x = u + dx
                if x < 0 or x >= width:
                    continue
                neighbour = float(depth[y, x])
                if neighbour > 0.0:
                    difference = centre - neighbour
                    w = spatial[dy + radius, dx + radius] * math.exp(
                        -(difference * difference) / two_sigma_d2
                    )
                    total += w * neighbour
                    weights += w
        return total / weights

    @jit
    def binomial5(offset: int) -> float:
        """Tap `offset` (-2..2) of the 5x5 binomial kernel's 1-D factor [1 4 6 4 1] / 16."""
        a = abs(offset)
        if a == 0:
            return 0.375
        if a == 1:
            return 0.25
        return 0.0625

    @jit
    def pyrdown_depth_pixel(depth: Any, v: int, u: int, cutoff: float) -> float:
        """Edge-aware 5x5 Gaussian centred on (2v, 2u) of the finer level (pyramid_down_depth)."""
        height, width = depth.shape
        cv = 2 * v
        cu = 2 * u
        centre = float(depth[cv, cu])
        if not centre > 0.0:
            return 0.0
        total = 0.0
        weights = 0.0
        for dy in range(-2, 3):
            y = cv + dy
            if y < 0 or y >= height:
                continue
            for dx in range(-2, 3):
                x = cu + dx
                if x < 0 or x >= width:
                    continue
                neighbour = float(depth[y, x])
                if neighbour > 0.0 and abs(neighbour - centre) <= cutoff:
                    w = binomial5(dy) * binomial5(dx)
                    total += w * neighbour
                    weights += w
        return total / weights

    @jit
    def pyrdown_intensity_pixel(image: Any, v: int, u: int) -> float:
        """5x5 Gaussian centred on (2v, 2u), renormalised over the taps inside the image."""
        height, width = image.shape
        total = 0.0
        weights = 0.0
        for dy in range(-2, 3):
            y = 2 * v + dy
            if y < 0 or y >= height:
                continue
            for dx in range(-2, 3):
                x = 2 * u + dx
                if x < 0 or x >= width:
                    continue
                w = binomial5(dy) * binomial5(dx)
                total += w * float(image[y, x])
                weights += w
        return total / weights

    @jit
    def vertex_pixel(
        depth: Any, v: int, u: int, fx: float, fy: float, cx: float, cy: float
    ) -> tuple[float, float, float]:
        """V(u, v) = D K^-1 [u, v, 1] in float64 like camera.backproject; NaN where D <= 0."""
        d = float(depth[v, u])
        if d <= 0.0:
            return np.nan, np.nan, np.nan
        return (u - cx) * d / fx, (v - cy) * d / fy, d

    @jit
    def normal_pixel(vertices: Any, v: int, u: int) -> tuple[Any, Any, Any]:
        """Unit (V(u,v+1)-V) x (V(u+1,v)-V) in float32 like the reference's np.cross/norm."""
        height, width = vertices.shape[0], vertices.shape[1]
        if v + 1 >= height or u + 1 >= width:
            return np.float32(np.nan), np.float32(np.nan), np.float32(np.nan)
        p0 = np.float32(vertices[v, u, 0])
        p1 = np.float32(vertices[v, u, 1])
        p2 = np.float32(vertices[v, u, 2])
        a0 = np.float32(vertices[v + 1, u, 0]) - p0
        a1 = np.float32(vertices[v + 1, u, 1]) - p1
        a2 = np.float32(vertices[v + 1, u, 2]) - p2
        b0 = np.float32(vertices[v, u + 1, 0]) - p0
        b1 = np.float32(vertices[v, u + 1, 1]) - p1
        b2 = np.float32(vertices[v, u + 1, 2]) - p2
        n0 = np.float32(a1 * b2) - np.float32(a2 * b1)
        n1 = np.float32(a2 * b0) - np.float32(a0 * b2)
        n2 = np.float32(a0 * b1) - np.float32(a1 * b0)
        squared = np.float32(np.float32(n0 * n0) + np.float32(n1 * n1)) + np.float32(n2 * n2)
        length = np.float32(math.sqrt(squared))
        if not length > 0:  # also NaN: a missing neighbour
            return np.float32(np.nan), np.float32(np.nan), np.float32(np.nan)
        return n0 / length, n1 / length, n2 / length

    @jit
    def intensity_pixel(r: Any, g: Any, b: Any) -> Any:
        """I = 0.299 R + 0.587 G + 0.114 B in float32 (NumPy 2 keeps the reference in float32)."""
        return (np.float32(0.299) * np.float32(r) + np.float32(0.587) * np.float32(g)) + np.float32(
            0.114
        ) * np.float32(b)

    @jit
    def correlate3x3_pixel(image: Any, v: int, u: int, kernel: Any) -> float:
        """3x3 correlation at (v, u) with replicated borders, summed in the reference's order."""
        height, width = image.shape
        total = 0.0
        for dy in range(3):
            y = min(max(v + dy - 1, 0), height - 1)
            for dx in range(3):
                x = min(max(u + dx - 1, 0), width - 1)
                total += kernel[dy, dx] * float(image[y, x])
        return total

    @jit
    def discontinuity_pixel(
        depth: Any, v: int, u: int, radius: int, jump: Any, max_bad: int
    ) -> bool:
        """True where colour may be fused: depth here and at most max_bad neighbours in the window
        further than `jump` (float32, as NumPy 2 compares) away; outside neighbours never count."""
        height, width = depth.shape
        centre = np.float32(depth[v, u])
        if not centre > 0:
            return False
        bad = 0
        for dy in range(-radius, radius + 1):
            y = v + dy
            if y < 0 or y >= height:
                continue
            for dx in range(-radius, radius + 1):
                x = u + dx
                if x < 0 or x >= width or (dy == 0 and dx == 0):
                    continue
                if abs(np.float32(depth[y, x]) - centre) > jump:
                    bad += 1
        return bad <= max_bad

    return SimpleNamespace(
        metric_value=metric_value,
        bilateral_pixel=bilateral_pixel,
        binomial5=binomial5,
        pyrdown_depth_pixel=pyrdown_depth_pixel,
        pyrdown_intensity_pixel=pyrdown_intensity_pixel,
        vertex_pixel=vertex_pixel,
        normal_pixel=normal_pixel,
        intensity_pixel=intensity_pixel,
        correlate3x3_pixel=correlate3x3_pixel,
        discontinuity_pixel=discontinuity_pixel,
    )
