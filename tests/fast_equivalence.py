"""Shared cases for the ref-vs-fast equivalence tests (not a test module itself).

The same checks run for the CPU backend (tests/test_fast_preprocess.py, in the main process)
and for the CUDA backend (tests/test_fast_cuda.py, on a GPU or in a subprocess with numba's
simulator). Each check calls a backend's function and its kintinuous_ref namesake on the same
input and compares with a tolerance stated at the check.

Inputs are built to hit the degenerate cases: a tilted plane with a box in front (depth edges of
0.4-0.6 m), holes, a hole at every image border, invalid raw values (NaN, negative, too far),
an all-zero depth map and a frame with a single valid pixel.
"""

from __future__ import annotations

from types import ModuleType

import numpy as np

from kintinuous_ref import preprocess as ref
from kintinuous_ref.camera import Intrinsics
from kintinuous_ref.config import PreprocessConfig

# Fewer parameter combinations per check (set by the CUDA tests when they run on the simulator,
# where every launch costs seconds); the degenerate inputs are kept.
QUICK = False


def camera_for(height: int, width: int) -> Intrinsics:
    """A camera with the TUM field of view for a small image."""
    scale = width / 640.0
    return Intrinsics(
        525.0 * scale, 525.0 * scale, (width - 1) / 2, (height - 1) / 2, width, height
    )


def scene_depth(height: int, width: int, seed: int = 0) -> np.ndarray:
    """Metric float32 depth: a tilted wall, a box 0.5 m in front of it, sensor-like noise,
    holes inside and along every border, and one isolated valid pixel."""
    rng = np.random.default_rng(seed)
    v, u = np.mgrid[0:height, 0:width]
    depth = 2.0 + 0.6 * u / width + 0.3 * v / height
    box = (u > width // 4) & (u < width // 2) & (v > height // 3) & (v < 2 * height // 3)
    depth = np.where(box, depth - 0.5, depth)
    depth = depth + 0.003 * rng.standard_normal(depth.shape)
    depth[rng.random(depth.shape) < 0.03] = 0.0  # scattered dropouts
    depth[height // 2 : height // 2 + 3, 3 * width // 4 : 3 * width // 4 + 4] = 0.0  # a hole
    depth[0, : width // 3] = 0.0  # holes touching each border
    depth[-1, width // 2 :] = 0.0
    depth[: height // 4, 0] = 0.0
    depth[height // 2 :, -1] = 0.0
    depth[height - 6 : height - 1, 1:6] = 0.0  # an isolated valid pixel in a hole
    depth[height - 4, 3] = 1.7
    return depth.astype(np.float32)


def raw_depth(height: int, width: int, seed: int = 0) -> np.ndarray:
    """TUM-style uint16 (5000 per metre) of scene_depth, with a few readings beyond 6 m."""
    raw = np.round(scene_depth(height, width, seed) * 5000.0).astype(np.uint16)
    raw[1, 1:5] = 65000  # 13 m: dropped as too far
    return raw


def float_depth_with_junk(height: int, width: int, seed: int = 0) -> np.ndarray:
    """float64 metres with NaN, inf, negative and too-far values besides valid ones."""
    depth = scene_depth(height, width, seed).astype(np.float64)
    depth[2, 2:6] = [np.nan, np.inf, -1.0, 7.5]
    depth[3, 2] = 6.0  # exactly max_depth: kept
    return depth


def scene_colour(height: int, width: int, seed: int = 0) -> np.ndarray:
    """uint8 RGB: smooth ramps plus noise, saturated corners (0 and 255)."""
    rng = np.random.default_rng(seed + 1)
    v, u = np.mgrid[0:height, 0:width]
    base = np.stack([255 * u / width, 255 * v / height, 128 + 100 * np.sin(u / 5.0)], axis=-1)
    colour = np.clip(base + rng.normal(0, 20, base.shape), 0, 255).astype(np.uint8)
    colour[0, 0] = 255
    colour[-1, -1] = 0
    return colour


def depth_cases(height: int, width: int) -> dict[str, np.ndarray]:
    """Named metric depth maps: the scene, nothing at all, and one lonely pixel."""
    lonely = np.zeros((height, width), np.float32)
    lonely[height // 2, width // 2] = 1.5
    return {
        "scene": scene_depth(height, width),
        "empty": np.zeros((height, width), np.float32),
        "single": lonely,
    }


# ----------------------------------------------------------------------------------------------
# Comparison


def assert_equivalent(
    name: str, fast: np.ndarray, reference: np.ndarray, atol: float = 0.0, rtol: float = 0.0
) -> None:
    """Same shape and dtype, NaN in exactly the same places, values within atol + rtol |ref|."""
    fast = np.asarray(fast)
    assert fast.shape == reference.shape, f"{name}: shape {fast.shape} != {reference.shape}"
    assert fast.dtype == reference.dtype, f"{name}: dtype {fast.dtype} != {reference.dtype}"
    if reference.dtype.kind != "f":
        mismatches = int(np.count_nonzero(fast != reference))
        assert mismatches == 0, f"{name}: {mismatches} elements differ"
        return
    nan_fast, nan_ref = np.isnan(fast), np.isnan(reference)
    assert np.array_equal(nan_fast, nan_ref), (
        f"{name}: NaN pattern differs at {int(np.count_nonzero(nan_fast != nan_ref))} elements"
    )
    ok = ~nan_ref
    np.testing.assert_allclose(fast[ok], reference[ok], atol=atol, rtol=rtol, err_msg=name)


# ----------------------------------------------------------------------------------------------
# Checks, one per public function of preprocess. Tolerances: the ops repeat the reference's
# arithmetic (same formula, order, precision), so most results are bit-identical. Where exp()
# enters (bilateral filter), NumPy's and the target's exp may differ by one unit in the last
# place (~1e-16 relative); after rounding to float32 that is at most one float32 ulp of the depth,
# 6 m * 2^-24 = 3.6e-7 m, hence rtol 2.4e-7 (two ulps). Normals computed from such a vertex
# differ by (ulp / neighbour spacing): 4e-7 m / 4 mm = 1e-4 at most at 160x120.


def check_metric_depth(impl: ModuleType, height: int, width: int) -> None:
    for name, depth in (
        ("uint16", raw_depth(height, width)),
        ("float64 with NaN/inf/<0/far", float_depth_with_junk(height, width)),
        ("float32", scene_depth(height, width)),
    ):
        assert_equivalent(
            f"metric_depth {name}",
            impl.metric_depth(depth, 6.0, 5000.0),
            ref.metric_depth(depth, 6.0, 5000.0),
        )


def check_bilateral_filter(impl: ModuleType, height: int, width: int, radius: int = 6) -> None:
    for name, depth in depth_cases(height, width).items():
        assert_equivalent(
            f"bilateral_filter {name}",
            impl.bilateral_filter(depth, 4.5, 0.03, radius),
            ref.bilateral_filter(depth, 4.5, 0.03, radius),
            rtol=2.4e-7,
        )


def check_pyramid_down(impl: ModuleType, height: int, width: int) -> None:
    for name, depth in depth_cases(height, width).items():
        assert_equivalent(
            f"pyramid_down_depth {name}",
            impl.pyramid_down_depth(depth, 0.09),
            ref.pyramid_down_depth(depth, 0.09),
        )
    # Odd sizes: the last row/column has no even partner, both drop it.
    odd = scene_depth(height - 1, width - 1)
    assert_equivalent(
        "pyramid_down_depth odd",
        impl.pyramid_down_depth(odd, 0.09),
        ref.pyramid_down_depth(odd, 0.09),
    )
    intensity = ref.intensity_image(scene_colour(height - 1, width - 1))
    assert_equivalent(
        "pyramid_down_intensity",
        impl.pyramid_down_intensity(intensity),
        ref.pyramid_down_intensity(intensity),
    )


def check_vertex_normal_maps(impl: ModuleType, height: int, width: int) -> None:
    camera = camera_for(height, width)
    for name, depth in depth_cases(height, width).items():
        vertices = ref.vertex_map(depth, camera)
        assert_equivalent(f"vertex_map {name}", impl.vertex_map(depth, camera), vertices)
        assert_equivalent(f"normal_map {name}", impl.normal_map(vertices), ref.normal_map(vertices))


def check_intensity(impl: ModuleType, height: int, width: int) -> None:
    colour = scene_colour(height, width)
    intensity = ref.intensity_image(colour)
    assert_equivalent("intensity_image", impl.intensity_image(colour), intensity)
    for sigma in (0.8,) if QUICK else (0.8, 2.0):
        fast_dx, fast_dy = impl.intensity_gradients(intensity, sigma)
        ref_dx, ref_dy = ref.intensity_gradients(intensity, sigma)
        assert_equivalent(f"intensity_dx sigma {sigma}", fast_dx, ref_dx)
        assert_equivalent(f"intensity_dy sigma {sigma}", fast_dy, ref_dy)


def check_discontinuity_mask(impl: ModuleType, height: int, width: int) -> None:
    for name, depth in depth_cases(height, width).items():
        combos = ((7, 0.2, 5),) if QUICK else ((7, 0.2, 5), (3, 0.1, 0), (5, 0.2, 24))
        for window, jump, max_bad in combos:
            assert_equivalent(
                f"discontinuity_mask {name} {window}x{window}",
                impl.discontinuity_mask(depth, window, jump, max_bad),
                ref.discontinuity_mask(depth, window, jump, max_bad),
            )
    # A jump of exactly float32(0.2) must compare as NumPy does (in float32, so: not bad).
    step = np.full((height, width), 1.0, np.float32)
    step[:, width // 2 :] = np.float32(1.0) + np.float32(0.2)
    assert_equivalent(
        "discontinuity_mask at the threshold",
        impl.discontinuity_mask(step, 7, 0.2, 0),
        ref.discontinuity_mask(step, 7, 0.2, 0),
    )


def check_preprocess_frame(
    impl: ModuleType, height: int, width: int, config: PreprocessConfig | None = None
) -> None:
    """The whole stage on raw uint16 depth: every array of every level."""
    config = config or PreprocessConfig()
    camera = camera_for(height, width)
    colour, depth = scene_colour(height, width), raw_depth(height, width)
    compare_frames(
        impl.preprocess_frame(colour, depth, camera, config),
        ref.preprocess_frame(colour, depth, camera, config),
    )


def compare_frames(fast: ref.PreprocessedFrame, reference: ref.PreprocessedFrame) -> None:
    """Every array of every level (host arrays)."""
    assert_equivalent("colour", fast.colour, reference.colour)
    assert_equivalent("depth", fast.depth, reference.depth)
    assert_equivalent("colour_mask", fast.colour_mask, reference.colour_mask)
    assert len(fast.levels) == len(reference.levels)
    for index, (a, b) in enumerate(zip(fast.levels, reference.levels, strict=True)):
        assert a.camera == b.camera
        assert_equivalent(f"level {index} depth", a.depth, b.depth)
        # vertices come from the bilateral-filtered depth: its tolerance carries over
        assert_equivalent(f"level {index} vertices", a.vertices, b.vertices, atol=1e-6, rtol=2.4e-7)
        assert_equivalent(f"level {index} normals", a.normals, b.normals, atol=1e-4)
        assert_equivalent(f"level {index} intensity", a.intensity, b.intensity)
        assert_equivalent(f"level {index} intensity_dx", a.intensity_dx, b.intensity_dx)
        assert_equivalent(f"level {index} intensity_dy", a.intensity_dy, b.intensity_dy)
