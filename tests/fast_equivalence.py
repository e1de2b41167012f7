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


# A GPU contracts a * b + c into one fused multiply-add (one rounding where NumPy rounds twice), so
# on real hardware float32 results may differ from the reference in the last bit. The CPU loops
# and the simulator round as NumPy does and stay bit-exact; test_fast_cuda.py sets CONTRACTED on a
# GPU, and the checks below that demand exactness then allow these tolerances instead.
CONTRACTED = False


def last_bits(atol: float) -> dict[str, float]:
    """{} (exact), or on a contracting GPU {atol, rtol}: a few float32 ulps of values whose
    magnitude makes `atol` a few ulps (1e-6 for unit normals, 1e-4 for 0..255 intensities)."""
    return {"atol": atol, "rtol": 1e-6} if CONTRACTED else {}


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
        assert_equivalent(
            f"normal_map {name}",
            impl.normal_map(vertices),
            ref.normal_map(vertices),
            **last_bits(1e-6),
        )


def check_intensity(impl: ModuleType, height: int, width: int) -> None:
    colour = scene_colour(height, width)
    intensity = ref.intensity_image(colour)
    assert_equivalent("intensity_image", impl.intensity_image(colour), intensity, **last_bits(1e-4))
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
        for name in ("intensity", "intensity_dx", "intensity_dy"):
            assert_equivalent(
                f"level {index} {name}",
                getattr(a, name),
                getattr(b, name),
                **last_bits(1e-4),
            )


# ----------------------------------------------------------------------------------------------
# TSDF integration and raycasting. The fast volume stores int16 TSDF (units of 1/32767), integer
# weights and uint8 colour + integer colour weight (8 bytes per voxel); the reference keeps
# float32. Weights are integers in both (+1 per frame), so they must agree exactly; each TSDF
# update rounds to the nearest 1/32767 (<= 0.5 unit) and earlier rounding errors are carried
# with the factor W / (W + 1) < 1, so after n frames |F_fast - F_ref| <= 0.5 n / 32767 (plus
# float32 arithmetic, 1e-7). The same argument bounds the colour (uint8 rounding) by 0.5 n
# levels when every colour weight is 1.


def moving_poses(frames: int) -> list[np.ndarray]:
    """Camera-to-world poses sliding sideways 1 cm and turning 1 degree per frame."""
    poses = []
    for n in range(frames):
        angle = np.radians(1.0 * n)
        pose = np.eye(4)
        pose[:3, :3] = [
            [np.cos(angle), 0, np.sin(angle)],
            [0, 1, 0],
            [-np.sin(angle), 0, np.cos(angle)],
        ]
        pose[:3, 3] = [0.01 * n, 0.005 * n, 0.0]
        poses.append(pose)
    return poses


def fused_volumes(
    tsdf_impl: ModuleType,
    height: int,
    width: int,
    resolution: int,
    frames: int,
    weighted: bool,
) -> tuple:
    """(fast volume, reference volume) after fusing `frames` frames of the scene."""
    from kintinuous_ref import colour as ref_colour
    from kintinuous_ref import tsdf as ref_tsdf
    from kintinuous_ref.config import ColourConfig, VolumeConfig

    camera = camera_for(height, width)
    config = VolumeConfig(resolution=resolution, size=3.0)
    poses = moving_poses(frames)
    fast = tsdf_impl.make_volume(config, poses[0])
    reference = ref_tsdf.make_volume(config, poses[0])
    colour = scene_colour(height, width)
    for index, pose in enumerate(poses):
        depth = scene_depth(height, width, seed=index)
        weights = None
        if weighted:
            frame = ref.preprocess_frame(colour, depth, camera, PreprocessConfig(pyramid_levels=1))
            weights = ref_colour.colour_weights(frame, ColourConfig())
        tsdf_impl.integrate(fast, depth, pose, camera, colour, weights)
        ref_tsdf.integrate(reference, depth, pose, camera, colour, weights)
    return fast, reference


def check_integrate(tsdf_impl: ModuleType, height: int, width: int, resolution: int) -> None:
    from kintinuous_fast.tsdf.volume import to_reference_volume

    frames = 3
    fast, reference = fused_volumes(tsdf_impl, height, width, resolution, frames, weighted=False)
    back = to_reference_volume(fast)
    assert np.count_nonzero(reference.weight) > 0.02 * reference.weight.size  # a real test
    assert_equivalent("weight", back.weight, reference.weight)
    assert_equivalent("tsdf", back.tsdf, reference.tsdf, atol=0.5 * frames / 32767 + 1e-7)
    assert_equivalent("colour weight > 0", back.colour_weight > 0, reference.colour_weight > 0)
    coloured = reference.colour_weight > 0
    np.testing.assert_allclose(back.colour[coloured], reference.colour[coloured], atol=0.5 * frames)
    np.testing.assert_array_equal(back.colour_weight, reference.colour_weight)  # all weights 1


def check_integrate_weighted_colour(
    tsdf_impl: ModuleType, height: int, width: int, resolution: int
) -> None:
    # Fractional colour weights (cos theta, paper eq. 15) are stored rounded to integers (at
    # least 1): the first observation is exact (C = rgb for any weight), later ones mix with
    # ratios w / (W' + w) instead of w / (W + w), |W' - W| <= 1. With this scene's colour
    # differences between frames (a few levels) that moves the colour by a few levels at most.
    from kintinuous_fast.tsdf.volume import to_reference_volume

    fast, reference = fused_volumes(tsdf_impl, height, width, resolution, 1, weighted=True)
    back = to_reference_volume(fast)
    coloured = reference.colour_weight > 0
    assert_equivalent("colour weight > 0", back.colour_weight > 0, coloured)
    np.testing.assert_allclose(back.colour[coloured], reference.colour[coloured], atol=0.5)
    fast, reference = fused_volumes(tsdf_impl, height, width, resolution, 3, weighted=True)
    back = to_reference_volume(fast)
    coloured = reference.colour_weight > 0
    difference = np.abs(back.colour[coloured] - reference.colour[coloured])
    assert difference.max() <= 8.0 and difference.mean() <= 0.5, (
        difference.max(),
        difference.mean(),
    )


def check_integrate_degenerate(tsdf_impl: ModuleType, height: int, width: int) -> None:
    """No depth, a camera looking away from the volume, a wrong-sized image."""
    from kintinuous_fast.tsdf.volume import to_reference_volume
    from kintinuous_ref.config import VolumeConfig
    from kintinuous_ref.errors import DatasetError

    camera = camera_for(height, width)
    config = VolumeConfig(resolution=16, size=1.0)
    volume = tsdf_impl.make_volume(config, np.eye(4))
    tsdf_impl.integrate(volume, np.zeros((height, width), np.float32), np.eye(4), camera)
    away = np.eye(4)
    away[:3, :3] = np.diag([-1.0, 1.0, -1.0])  # turned round: the volume is behind the camera
    tsdf_impl.integrate(
        volume, scene_depth(height, width), away, camera, scene_colour(height, width)
    )
    back = to_reference_volume(volume)
    assert not back.weight.any() and not back.colour_weight.any()
    try:
        tsdf_impl.integrate(volume, np.zeros((height + 1, width), np.float32), np.eye(4), camera)
    except DatasetError as err:
        assert "depth image is" in str(err)
    else:
        raise AssertionError("a wrong-sized depth image was accepted")


# sample_tsdf: the same float64 products of the same (dequantised) values, summed as trees where
# the reference sums in a chain (tsdf.voxel.sample_tsdf_at). Eight terms of |w F| <= 1 over a
# coverage near 1 differ by a few ulps of 1 at most.
SAMPLE_TSDF_ATOL = 2e-15


def check_sample_tsdf(tsdf_impl: ModuleType, height: int, width: int, resolution: int) -> None:
    from kintinuous_fast.tsdf.volume import to_reference_volume
    from kintinuous_ref import tsdf as ref_tsdf

    fast, _ = fused_volumes(tsdf_impl, height, width, resolution, 1, weighted=False)
    rng = np.random.default_rng(3)
    coordinates = rng.uniform(-1.0, resolution, (500, 3))
    coordinates[:3] = [[0, 0, 0], [resolution - 1] * 3, [np.nan, 1, 1]]
    assert_equivalent(
        "sample_tsdf",
        np.asarray(tsdf_impl.sample_tsdf(fast, coordinates)),
        ref_tsdf.sample_tsdf(to_reference_volume(fast), coordinates),
        atol=SAMPLE_TSDF_ATOL,
    )


def check_raycast(
    tsdf_impl: ModuleType, raycast_impl: ModuleType, height: int, width: int, resolution: int
) -> None:
    """Raycast the fast volume and the reference on the same (dequantised) volume from the
    fused poses, from a pose looking away, and from inside an empty volume.

    Tolerances: ray directions come from R K^-1 [u, v, 1] evaluated in the kernel, the
    reference's from a BLAS matrix product: they may differ in the last bit (1e-16), which moves
    samples by ~1e-16 m; vertices (float32) by 1 ulp, normals by 1e-6 at most (the reference's
    float32 samples, test_equivalence_cpu_gradient_normal). A ray that grazes a zero crossing
    could flip between hit and miss: at most 0.2% of the pixels may.
    """
    from kintinuous_fast.tsdf.volume import to_reference_volume
    from kintinuous_ref import raycast as ref_raycast

    fast, _ = fused_volumes(tsdf_impl, height, width, resolution, 2, weighted=False)
    back = to_reference_volume(fast)
    camera = camera_for(height, width)
    away = np.eye(4)
    away[:3, :3] = np.diag([-1.0, 1.0, -1.0])
    for name, pose in (
        ("first", moving_poses(2)[0]),
        ("second", moving_poses(2)[1]),
        ("away", away),
    ):
        got = raycast_impl.raycast(fast, pose, camera)
        want = ref_raycast.raycast(back, pose, camera)
        hit_got, hit_want = ~np.isnan(got.vertices[..., 0]), ~np.isnan(want.vertices[..., 0])
        flipped = np.count_nonzero(hit_got != hit_want)
        assert flipped <= 0.002 * hit_want.size, f"raycast {name}: {flipped} pixels flip"
        if name != "away":
            assert hit_want.mean() > 0.3, f"raycast {name}: the surface is not in view"
        else:
            assert not hit_want.any()
        both = hit_got & hit_want
        np.testing.assert_allclose(got.vertices[both], want.vertices[both], atol=1e-5, rtol=0)
        np.testing.assert_allclose(got.normals[both], want.normals[both], atol=1e-5, rtol=0)
        assert np.abs(got.colours[both].astype(int) - want.colours[both]).max(initial=0) <= 1
        assert not got.colours[~hit_got].any()
        np.testing.assert_array_equal(got.pose, want.pose)
    # The pipeline's prediction leaves colour out: the same geometry, a black colour map.
    view = moving_poses(2)[1]
    uncoloured = raycast_impl.raycast(fast, view, camera, colour=False)
    coloured = raycast_impl.raycast(fast, view, camera)
    np.testing.assert_array_equal(uncoloured.vertices, coloured.vertices)
    np.testing.assert_array_equal(uncoloured.normals, coloured.normals)
    assert coloured.colours.any() and not uncoloured.colours.any()
    # A stride casts every s-th pixel of each every s-th row (tiles and pairs regrouped):
    # each ray's answer is the full raycast's, bit for bit; the other pixels stay empty.
    for stride in (2, 3):
        strided = raycast_impl.raycast(fast, view, camera, stride=stride)
        cast = np.zeros((camera.height, camera.width), dtype=bool)
        cast[::stride, ::stride] = True
        for name in ("vertices", "normals", "colours"):
            got_map, full_map = getattr(strided, name), getattr(coloured, name)
            np.testing.assert_array_equal(got_map[cast], full_map[cast], err_msg=name)
        assert np.isnan(strided.vertices[~cast]).all() and not strided.colours[~cast].any()
