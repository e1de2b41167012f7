"""Per-pixel maths of kintinuous_ref.preprocess, written once for the CPU and the CUDA target.

Every `*_pixel` function computes ONE output pixel exactly as the reference computes the whole
image (same formula, same order of summation, same float32/float64 choices), so the backends agree
with the reference to the last bit or the last unit in the last place. Neighbours outside the
image are skipped where the reference fills them with a value that does not contribute (a weight
times 0, or NaN in a comparison), which leaves every sum unchanged. The CUDA kernels call the
`*_pixel` functions once per thread; the CPU loops run a filter tap by tap along a row (so that
LLVM vectorises them) and call the smaller functions those are made of: one tap's contribution
(`depth_tap_counts`, `is_depth_jump`, `bilateral_weight`) and one pixel's result from its sums.

The bilateral filter computes differently from the reference, within 2 float32 ulps of it:
float32 weights from a polynomial exp, and sums of differences from the centre,
D'(p) = D(p) + sum_q w (D(q) - D(p)) / (1 + sum_q w), the centre weighing exp(0) = 1. The
correction is a few millimetres, so its float32 rounding (and the weights' 1-2 ulp) moves the
result far less than one float32 ulp of the depth; the float64 addition of the centre and the
division then round as the reference does (tests/test_fast_preprocess.py states the tolerance).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from types import SimpleNamespace
from typing import Any

import numpy as np

_LOG2E = np.float32(1.4426950408889634)
# ln 2 split so that n * _LN2_HI is exact for every n used here (Cody-Waite reduction): r is then
# accurate with or without FMA contraction.
_LN2_HI = np.float32(0.693359375)
_LN2_LO = np.float32(-2.12194440e-4)
EXP_MAX = np.float32(80.0)  # exp(-80) = 1.8e-35: such weights are left out


def build_ops(
    jit: Callable[[Any], Any],
    weight_jit: Callable[[Any], Any],
    power_of_two_neg: Callable[[Any], Any],
) -> SimpleNamespace:
    """The scalar functions of preprocessing compiled with `jit` (see kintinuous_fast.targets),
    in one namespace.

    `weight_jit` compiles the bilateral weights (the CPU contracts FMAs there and nowhere else:
    elsewhere that would change the reference's float32 rounding); `power_of_two_neg(n)` is the
    float32 2^-n for 0 <= n <= 126 compiled for the target."""
    parts = (
        build_metric_depth(jit),
        build_bilateral(jit, weight_jit, power_of_two_neg),
        build_pyramid(jit),
        build_vertices_and_normals(jit),
        build_intensity(jit),
        build_discontinuity(jit),
    )
    return SimpleNamespace(**{name: f for part in parts for name, f in vars(part).items()})


def build_metric_depth(jit: Callable[[Any], Any]) -> SimpleNamespace:
    """A raw depth value in metres."""

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

    return SimpleNamespace(metric_value=metric_value)


def build_bilateral(
    jit: Callable[[Any], Any],
    weight_jit: Callable[[Any], Any],
    power_of_two_neg: Callable[[Any], Any],
) -> SimpleNamespace:
    """The bilateral filter's weights (`weight_jit`) and its per-pixel result."""

    @weight_jit
    def exp_neg(x: Any) -> Any:
        """exp(-x) for float32 0 <= x <= 80, within 2.4e-7 relative: x = n ln2 + r, |r| <= ln2/2,
        exp(-r) by its degree-6 Taylor polynomial, times 2^-n. No branch and no libm call, so
        the CPU's row loops vectorise it."""
        n = np.int32(x * _LOG2E + np.float32(0.5))
        nf = np.float32(n)
        r = (x - nf * _LN2_HI) - nf * _LN2_LO
        p = np.float32(1.0 / 720.0)
        p = p * r - np.float32(1.0 / 120.0)
        p = p * r + np.float32(1.0 / 24.0)
        p = p * r - np.float32(1.0 / 6.0)
        p = p * r + np.float32(0.5)
        p = p * r - np.float32(1.0)
        p = p * r + np.float32(1.0)
        return p * power_of_two_neg(n)

    @weight_jit
    def bilateral_weight(difference: Any, spatial: Any, inv_two_sigma2: Any) -> Any:
        """float32 exp(-spatial - difference^2 / 2 sigma_d^2) of a pixel pair whose depths differ
        by `difference`, `spatial` being the spatial Gaussian's exponent of their offset; 0
        beyond exp(-80) (a select, not a branch, so that the CPU's loops vectorise)."""
        x = difference * difference * inv_two_sigma2 + spatial
        return exp_neg(min(x, EXP_MAX)) if x < EXP_MAX else np.float32(0.0)

    @jit
    def bilateral_result(centre: Any, sum_w: float, sum_wd: float) -> Any:
        """D'(p) = D(p) + sum_q w (D(q) - D(p)) / (1 + sum_q w) in float64 from the float32
        centre and the sums of its neighbours' weights and weighted differences; 0 in holes."""
        filtered = np.float32(float(centre) + sum_wd / (1.0 + sum_w))
        return filtered if centre > np.float32(0.0) else np.float32(0.0)

    @jit
    def bilateral_pixel(
        depth: Any, v: int, u: int, spatial: Any, radius: int, inv_two_sigma2: Any
    ) -> Any:
        """Bilateral filter at (v, u) over a (2 radius + 1)^2 window; `spatial` holds the spatial
        Gaussian's float32 exponents. Holes (depth <= 0 or NaN) neither weigh nor are filled."""
        height, width = depth.shape
        centre = np.float32(depth[v, u])
        if not centre > np.float32(0.0):
            return np.float32(0.0)
        sum_w = np.float32(0.0)
        sum_wd = np.float32(0.0)
        for dy in range(-radius, radius + 1):
            y = v + dy
            if y < 0 or y >= height:
                continue
            for dx in range(-radius, radius + 1):
                x = u + dx
                if x < 0 or x >= width or (dy == 0 and dx == 0):
                    continue
                neighbour = np.float32(depth[y, x])
                if neighbour > np.float32(0.0):
                    difference = neighbour - centre
                    w = bilateral_weight(
                        difference, spatial[dy + radius, dx + radius], inv_two_sigma2
                    )
                    sum_w += w
                    sum_wd += w * difference
        return bilateral_result(centre, float(sum_w), float(sum_wd))

    return SimpleNamespace(
        bilateral_pixel=bilateral_pixel,
        bilateral_result=bilateral_result,
        bilateral_weight=bilateral_weight,
        exp_neg=exp_neg,
    )


def build_pyramid(jit: Callable[[Any], Any]) -> SimpleNamespace:
    """The 5x5 Gaussian pyramids: edge-aware for depth, renormalised at the border for intensity."""

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
    def depth_tap_counts(centre: float, neighbour: float, cutoff: float) -> bool:
        """Whether a tap of the edge-aware pyramid weighs: a depth within `cutoff` of the
        centre's (float64, as pyramid_down_depth)."""
        return (neighbour > 0.0) & (abs(neighbour - centre) <= cutoff)

    @jit
    def pyrdown_depth_result(centre: float, total: float, weights: float) -> Any:
        """The weighted mean of the taps that count; 0 where the centre is a hole."""
        return np.float32(total / weights) if centre > 0.0 else np.float32(0.0)

    @jit
    def pyrdown_depth_pixel(depth: Any, v: int, u: int, cutoff: float) -> Any:
        """Edge-aware 5x5 Gaussian centred on (2v, 2u) of the finer level (pyramid_down_depth)."""
        height, width = depth.shape
        cv = 2 * v
        cu = 2 * u
        centre = float(depth[cv, cu])
        if not centre > 0.0:
            return np.float32(0.0)
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
                if depth_tap_counts(centre, neighbour, cutoff):
                    w = binomial5(dy) * binomial5(dx)
                    total += w * neighbour
                    weights += w
        return pyrdown_depth_result(centre, total, weights)

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

    return SimpleNamespace(
        binomial5=binomial5,
        depth_tap_counts=depth_tap_counts,
        pyrdown_depth_pixel=pyrdown_depth_pixel,
        pyrdown_depth_result=pyrdown_depth_result,
        pyrdown_intensity_pixel=pyrdown_intensity_pixel,
    )


def build_vertices_and_normals(jit: Callable[[Any], Any]) -> SimpleNamespace:
    """Vertex maps from depth, normal maps from vertices."""

    @jit
    def vertex_from_depth(d: float, u: int, v: int, camera: Any) -> tuple[float, float, float]:
        """D K^-1 [u, v, 1] in float64 like camera.backproject, `camera` = (fx, fy, cx, cy);
        NaN where D <= 0."""
        fx, fy, cx, cy = camera
        if not d > 0.0:
            return np.nan, np.nan, np.nan
        return (u - cx) * d / fx, (v - cy) * d / fy, d

    @jit
    def vertex_pixel(depth: Any, v: int, u: int, camera: Any) -> tuple[float, float, float]:
        """V(u, v) of a depth map (vertex_from_depth)."""
        return vertex_from_depth(float(depth[v, u]), u, v, camera)

    @jit
    def normal_from_edges(
        a0: Any, a1: Any, a2: Any, b0: Any, b1: Any, b2: Any
    ) -> tuple[Any, Any, Any]:
        """Unit a x b in float32 like the reference's np.cross/norm, a = V(u,v+1) - V and
        b = V(u+1,v) - V (float32); NaN where a neighbour is missing or the edges are parallel."""
        n0 = np.float32(a1 * b2) - np.float32(a2 * b1)
        n1 = np.float32(a2 * b0) - np.float32(a0 * b2)
        n2 = np.float32(a0 * b1) - np.float32(a1 * b0)
        squared = np.float32(np.float32(n0 * n0) + np.float32(n1 * n1)) + np.float32(n2 * n2)
        length = np.float32(math.sqrt(squared))
        valid = length > np.float32(0.0)  # also NaN: a missing neighbour
        missing = np.float32(np.nan)
        return (
            n0 / length if valid else missing,
            n1 / length if valid else missing,
            n2 / length if valid else missing,
        )

    @jit
    def normal_pixel(vertices: Any, v: int, u: int) -> tuple[Any, Any, Any]:
        """The normal at (v, u) of a vertex map; NaN on the last row and column."""
        height, width = vertices.shape[0], vertices.shape[1]
        if v + 1 >= height or u + 1 >= width:
            return np.float32(np.nan), np.float32(np.nan), np.float32(np.nan)
        p0 = np.float32(vertices[v, u, 0])
        p1 = np.float32(vertices[v, u, 1])
        p2 = np.float32(vertices[v, u, 2])
        return normal_from_edges(
            np.float32(vertices[v + 1, u, 0]) - p0,
            np.float32(vertices[v + 1, u, 1]) - p1,
            np.float32(vertices[v + 1, u, 2]) - p2,
            np.float32(vertices[v, u + 1, 0]) - p0,
            np.float32(vertices[v, u + 1, 1]) - p1,
            np.float32(vertices[v, u + 1, 2]) - p2,
        )

    return SimpleNamespace(
        normal_from_edges=normal_from_edges,
        normal_pixel=normal_pixel,
        vertex_from_depth=vertex_from_depth,
        vertex_pixel=vertex_pixel,
    )


def build_intensity(jit: Callable[[Any], Any]) -> SimpleNamespace:
    """Intensity from colour, and the 3x3 correlations of its gradients."""

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

    return SimpleNamespace(correlate3x3_pixel=correlate3x3_pixel, intensity_pixel=intensity_pixel)


def build_discontinuity(jit: Callable[[Any], Any]) -> SimpleNamespace:
    """The depth-discontinuity check of colour fusion (paper VI-B)."""

    @jit
    def is_depth_jump(centre: Any, neighbour: Any, jump: Any) -> bool:
        """|D(q) - D(p)| > jump in float32, as NumPy compares (NaN: never)."""
        return abs(np.float32(neighbour) - np.float32(centre)) > jump

    @jit
    def colour_fusable(centre: Any, bad: int, max_bad: int) -> bool:
        """Depth at the pixel and at most max_bad jumps to its neighbours."""
        return np.float32(centre) > np.float32(0.0) and bad <= max_bad

    @jit
    def discontinuity_pixel(
        depth: Any, v: int, u: int, radius: int, jump: Any, max_bad: int
    ) -> bool:
        """True where colour may be fused (colour_fusable over the window's neighbours);
        outside neighbours never count."""
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
                if is_depth_jump(centre, depth[y, x], jump):
                    bad += 1
        return colour_fusable(centre, bad, max_bad)

    return SimpleNamespace(
        colour_fusable=colour_fusable,
        discontinuity_pixel=discontinuity_pixel,
        is_depth_jump=is_depth_jump,
    )
