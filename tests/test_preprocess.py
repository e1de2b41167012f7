"""Preprocessing against closed forms: filters of constants and ramps, normals of planes,
the depth-edge-aware pyramid, Sobel slopes and the 7x7 discontinuity mask on hand-made depth."""

import numpy as np
import pytest

from kintinuous_ref import preprocess
from kintinuous_ref.camera import Intrinsics
from kintinuous_ref.config import PreprocessConfig
from kintinuous_ref.errors import DatasetError

CAMERA = Intrinsics(160.0, 160.0, 79.5, 59.5, 160, 120)
CONFIG = PreprocessConfig()


def ramp(a: float = 0.002, b: float = 0.001, c: float = 1.5) -> np.ndarray:
    v, u = np.mgrid[0:120, 0:160]
    return (c + a * u + b * v).astype(np.float32)


def test_bilateral_keeps_constants_and_linear_ramps():
    # The weights are symmetric about the centre for a linear ramp (|D(p)-D(q)| is the same for
    # q and its mirror image), so the weighted mean is exactly the centre value away from the
    # border; float32 storage limits agreement to ~1e-6 m.
    depth = ramp()
    filtered = preprocess.bilateral_filter(depth, 4.5, 0.03, 6)
    np.testing.assert_allclose(filtered[6:-6, 6:-6], depth[6:-6, 6:-6], atol=2e-6)
    constant = np.full((120, 160), 2.0, np.float32)
    np.testing.assert_allclose(preprocess.bilateral_filter(constant, 4.5, 0.03, 6), 2.0, atol=1e-6)


def test_bilateral_preserves_depth_edges_and_holes():
    depth = np.full((120, 160), 1.0, np.float32)
    depth[:, 80:] = 1.5
    depth[50:52, 20:22] = 0.0
    filtered = preprocess.bilateral_filter(depth, 4.5, 0.03, 6)
    # 0.5 m against sigma_depth = 0.03 m: range weight exp(-139) - the sides never mix.
    np.testing.assert_allclose(filtered[:, :80][depth[:, :80] > 0], 1.0, atol=1e-6)
    np.testing.assert_allclose(filtered[:, 80:], 1.5, atol=1e-6)
    assert np.all(filtered[50:52, 20:22] == 0.0)


def test_depth_pyramid_of_constant_and_across_an_edge():
    constant = np.full((120, 160), 1.25, np.float32)
    half = preprocess.pyramid_down_depth(constant, 0.09)
    assert half.shape == (60, 80)
    np.testing.assert_allclose(half, 1.25, atol=1e-6)
    step = np.full((120, 160), 1.0, np.float32)
    step[:, 81:] = 2.0  # the edge falls inside the 5x5 footprint of output column 40
    half = preprocess.pyramid_down_depth(step, 0.09)
    # Neighbours 1 m away are beyond 3 sigma_depth = 0.09 m: each side keeps its exact value.
    assert set(np.unique(half)) == {1.0, 2.0}
    np.testing.assert_array_equal(half[:, 40], 1.0)
    np.testing.assert_array_equal(half[:, 41], 2.0)


def test_intensity_and_its_pyramid():
    colour = np.zeros((120, 160, 3), np.uint8)
    colour[...] = (100, 50, 200)
    intensity = preprocess.intensity_image(colour)
    np.testing.assert_allclose(intensity, 0.299 * 100 + 0.587 * 50 + 0.114 * 200, rtol=1e-6)
    half = preprocess.pyramid_down_intensity(intensity)
    assert half.shape == (60, 80)
    np.testing.assert_allclose(half, intensity[0, 0], rtol=1e-6)


def test_sobel_gives_slope_per_pixel():
    # A Gaussian blur keeps a linear function and Sobel/8 of a + b u + c v is (b, c) exactly.
    v, u = np.mgrid[0:120, 0:160]
    intensity = (10.0 + 0.75 * u - 0.5 * v).astype(np.float32)
    dx, dy = preprocess.intensity_gradients(intensity, 0.8)
    np.testing.assert_allclose(dx[2:-2, 2:-2], 0.75, atol=1e-4)
    np.testing.assert_allclose(dy[2:-2, 2:-2], -0.5, atol=1e-4)


def test_normals_of_planes_point_to_the_camera():
    frontal = np.full((120, 160), 1.2, np.float32)
    normals = preprocess.normal_map(preprocess.vertex_map(frontal, CAMERA))
    np.testing.assert_allclose(
        normals[:-1, :-1], np.broadcast_to([0, 0, -1], (119, 159, 3)), atol=1e-6
    )
    assert np.isnan(normals[-1]).all() and np.isnan(normals[:, -1]).all()
    # Tilted plane n . X = d with n = (0.3, -0.2, -1)/|.|: depth along ray r is d / (n . r).
    n = np.array([0.3, -0.2, -1.0]) / np.linalg.norm([0.3, -0.2, -1.0])
    rays = CAMERA.ray_directions()
    depth = (-1.0 / (rays @ n)).astype(np.float32)  # n . X = -1, in front of the camera
    normals = preprocess.normal_map(preprocess.vertex_map(depth, CAMERA))
    # float32 vertices 1 mm apart give normals good to ~1e-3.
    np.testing.assert_allclose(normals[:-1, :-1].reshape(-1, 3) @ n, 1.0, atol=2e-3)


def test_vertices_are_backprojected_depth():
    depth = ramp()
    depth[3, 4] = 0.0
    vertices = preprocess.vertex_map(depth, CAMERA)
    u, v = 100, 30
    z = depth[v, u]
    np.testing.assert_allclose(
        vertices[v, u], [(u - 79.5) * z / 160, (v - 59.5) * z / 160, z], rtol=1e-6
    )
    assert np.isnan(vertices[3, 4]).all()


def test_discontinuity_mask_on_a_step():
    depth = np.full((120, 160), 1.0, np.float32)
    depth[:, 80:] = 1.5  # a 0.5 m step between columns 79 and 80
    mask = preprocess.discontinuity_mask(depth, 7, 0.2, 5)
    # A pixel whose 7x7 window reaches k columns across the edge has 7k bad neighbours (> 5 for
    # k >= 1): columns 77..82 are masked, all others fused (rows 3 .. 116, full windows).
    expected = np.ones(160, bool)
    expected[77:83] = False
    np.testing.assert_array_equal(mask[3:-3], np.broadcast_to(expected, (114, 160)))
    # In rows 0 and 1 only 4 or 5 window rows lie inside the image: columns 77 and 82 have
    # 4 or 5 bad neighbours (fused), column 78 has 8 or 10 (masked).
    assert mask[0, 77] and mask[1, 82] and not mask[0, 78] and not mask[2, 77]
    # A 0.1 m step is below the 0.2 m threshold: nothing masked.
    depth[:, 80:] = 1.1
    assert preprocess.discontinuity_mask(depth, 7, 0.2, 5).all()


def test_discontinuity_mask_small_holes_and_missing_depth():
    depth = np.full((120, 160), 1.0, np.float32)
    depth[60, 60:65] = 0.0  # 5 missing pixels in a row: at most 5 bad neighbours -> still fused
    depth[20:40, 20:40] = 0.0  # a large hole: its own pixels are never fused, its rim is masked
    mask = preprocess.discontinuity_mask(depth, 7, 0.2, 5)
    assert not mask[60, 60:65].any()
    assert mask[59, 60:65].all() and mask[61, 62]
    assert not mask[20:40, 20:40].any()
    assert not mask[30, 41] and not mask[30, 42] and mask[30, 43]  # 7 / 7 / 0 bad: 3 cols
    assert mask[30, 45]


def test_preprocess_frame_levels():
    colour = np.full((120, 160, 3), 128, np.uint8)
    depth = np.full((120, 160), 1.0, np.float32)
    frame = preprocess.preprocess_frame(colour, depth, CAMERA, CONFIG)
    assert len(frame.levels) == 4
    for level, data in enumerate(frame.levels):
        h, w = 120 >> level, 160 >> level
        assert data.depth.shape == (h, w) and data.vertices.shape == (h, w, 3)
        assert data.camera == CAMERA.at_level(level)
        np.testing.assert_allclose(data.depth, 1.0, atol=1e-6)
        np.testing.assert_allclose(data.vertices[..., 2], 1.0, atol=1e-6)
        np.testing.assert_allclose(data.intensity, 128.0, atol=1e-3)
        np.testing.assert_allclose(data.intensity_dx, 0.0, atol=1e-4)
    assert frame.colour_mask.all()


def test_preprocess_all_zero_depth_and_far_depth():
    colour = np.zeros((120, 160, 3), np.uint8)
    frame = preprocess.preprocess_frame(colour, np.zeros((120, 160), np.float32), CAMERA, CONFIG)
    assert np.isnan(frame.levels[0].vertices).all() and np.isnan(frame.levels[3].normals).all()
    assert not frame.colour_mask.any()
    far = np.full((120, 160), 7.0, np.float32)  # beyond max_depth = 6 m: dropped
    far[0, 0] = np.nan
    frame = preprocess.preprocess_frame(colour, far, CAMERA, CONFIG)
    assert (frame.depth == 0).all()


def test_preprocess_converts_raw_sensor_units():
    raw = np.full((120, 160), 7500, np.uint16)  # TUM: 5000 per metre
    frame = preprocess.preprocess_frame(np.zeros((120, 160, 3), np.uint8), raw, CAMERA, CONFIG)
    np.testing.assert_allclose(frame.depth, 1.5)


def test_preprocess_rejects_wrong_shapes():
    with pytest.raises(DatasetError, match="depth image"):
        preprocess.preprocess_frame(
            np.zeros((120, 160, 3), np.uint8), np.zeros((60, 80), np.float32), CAMERA, CONFIG
        )
    with pytest.raises(DatasetError, match="colour image"):
        preprocess.preprocess_frame(
            np.zeros((120, 160), np.uint8), np.zeros((120, 160), np.float32), CAMERA, CONFIG
        )


def test_model_pyramid_subsamples_nan_aware():
    vertices = preprocess.vertex_map(ramp(), CAMERA)
    normals = preprocess.normal_map(vertices)
    pyramid = preprocess.model_pyramid(vertices, normals, 3)
    assert [v.shape for v, _ in pyramid] == [(120, 160, 3), (60, 80, 3), (30, 40, 3)]
    v2, n2 = pyramid[2]
    np.testing.assert_array_equal(v2, vertices[::4, ::4])
    # A level-2 vertex projects onto its own pixel with the level-2 camera.
    uv = CAMERA.at_level(2).project(v2[10, 20].astype(np.float64))
    np.testing.assert_allclose(uv, [20, 10], atol=1e-3)
    vertices[8, 8] = np.nan  # an invalid model pixel on the level-2 grid stays invalid
    assert np.isnan(preprocess.model_pyramid(vertices, normals, 3)[2][0][2, 2]).all()
