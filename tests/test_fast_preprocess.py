"""Equivalence of kintinuous_fast's CPU preprocessing with kintinuous_ref.preprocess on small
frames (80x60 and 160x120) with holes, borders, depth edges, junk values and empty maps.
The cases and their tolerances are in tests/fast_equivalence.py; the CUDA twin of this file is
tests/test_fast_cuda.py.

Tolerance of the CPU bilateral filter: rtol 2.4e-7 (two float32 ulps of the depth), as if it
repeated the reference's float64 arithmetic, which it does not (for speed). Its weights
are float32 from a polynomial exp (<= 2.4e-7 relative, test below) and its sums are of
differences from the centre, D'(p) = D(p) + sum w (D(q) - D(p)) / sum w: a weight error eps moves
the result by at most eps times the weighted spread of the differences (millimetres), and the
float32 rounding of the sums acts on that correction only, not on the depth, so both stay far
below one ulp of the depth; D(p) + correction is added and rounded in float64 as the reference
rounds its quotient. Measured on redkitchen frames (640x480): at most 1 ulp, 0.65% of pixels.
"""

import fast_equivalence as fe
import numba
import numpy as np
import pytest

from kintinuous_fast.preprocess import cpu, cpu_bilateral
from kintinuous_ref import preprocess as ref
from kintinuous_ref.config import PreprocessConfig
from kintinuous_ref.errors import DatasetError

SIZES = [(60, 80), (120, 160)]


@pytest.mark.parametrize("size", SIZES, ids=["80x60", "160x120"])
@pytest.mark.parametrize(
    "check",
    [
        fe.check_metric_depth,
        fe.check_bilateral_filter,
        fe.check_pyramid_down,
        fe.check_vertex_normal_maps,
        fe.check_intensity,
        fe.check_discontinuity_mask,
        fe.check_preprocess_frame,
    ],
    ids=lambda check: check.__name__.removeprefix("check_"),
)
def test_equivalence_cpu_preprocess(check, size):
    check(cpu, *size)


def test_equivalence_cpu_preprocess_frame_other_config():
    # Non-default parameters reach the kernels: smaller window, 3 levels, looser cutoff.
    config = PreprocessConfig(
        bilateral_radius=3, pyramid_levels=3, pyramid_depth_cutoff=0.3, discontinuity_window=5
    )
    fe.check_preprocess_frame(cpu, 60, 80, config)


def test_cpu_model_pyramid_is_the_reference_subsampling():
    vertices = ref.vertex_map(fe.scene_depth(60, 80), fe.camera_for(60, 80))
    normals = ref.normal_map(vertices)
    fast = cpu.model_pyramid(vertices, normals, 3)
    assert [v.shape for v, _ in fast] == [(60, 80, 3), (30, 40, 3), (15, 20, 3)]
    np.testing.assert_array_equal(fast[2][0], vertices[::4, ::4])
    np.testing.assert_array_equal(fast[1][1], normals[::2, ::2])


def test_cpu_preprocess_frame_rejects_mismatched_images():
    camera = fe.camera_for(60, 80)
    with pytest.raises(DatasetError, match=r"depth image is \(60, 81\)"):
        cpu.preprocess_frame(
            fe.scene_colour(60, 80), np.zeros((60, 81), np.uint16), camera, PreprocessConfig()
        )
    with pytest.raises(DatasetError, match="colour image"):
        cpu.preprocess_frame(
            np.zeros((60, 80, 3), np.float32), fe.raw_depth(60, 80), camera, PreprocessConfig()
        )


@pytest.mark.parametrize("size", [(60, 80), (61, 81), (13, 40)], ids=["80x60", "81x61", "40x13"])
def test_equivalence_cpu_bilateral_filter_in_chunks(monkeypatch, size):
    # Frames this small run as one chunk; with the parallel split forced, row chunks of 7 rows
    # (the last shorter than the radius) must add their pair sums across every seam.
    monkeypatch.setattr(cpu_bilateral, "PARALLEL_MIN", 0)
    monkeypatch.setattr(cpu_bilateral, "CHUNK_ROWS", 7)
    fe.check_bilateral_filter(cpu, *size)
    fe.check_bilateral_filter(cpu, *size, radius=3)


def test_equivalence_cpu_preprocess_frame_in_chunks(monkeypatch):
    monkeypatch.setattr(cpu, "PARALLEL_MIN", 0)
    monkeypatch.setattr(cpu_bilateral, "PARALLEL_MIN", 0)
    monkeypatch.setattr(cpu_bilateral, "CHUNK_ROWS", 7)
    fe.check_preprocess_frame(cpu, 60, 80)


def test_cpu_bilateral_filter_is_the_same_bits_on_any_thread_count():
    # A 640x480 depth map runs in chunks; how many threads run them must not change a bit
    # (the chunks, and so the order of each seam row's sums, follow the image, not the threads).
    depth = fe.raw_depth(480, 640).astype(np.float32) / np.float32(5000.0)
    threads = numba.get_num_threads()
    try:
        results = []
        for count in sorted({1, numba.config.NUMBA_NUM_THREADS}):
            numba.set_num_threads(count)
            results.append(cpu_bilateral.bilateral_filter(depth, 4.5, 0.03, 3))
    finally:
        numba.set_num_threads(threads)
    assert all(np.array_equal(results[0], other, equal_nan=True) for other in results[1:])


@numba.njit  # not cached: the cache would not see a change of cpu_bilateral.exp_neg
def _exp_neg_of(x):
    out = np.empty_like(x)
    for i in range(x.shape[0]):
        out[i] = cpu_bilateral.exp_neg(x[i])
    return out


def test_cpu_bilateral_exp_is_accurate():
    # The polynomial exp(-x) of the bilateral weights: the error budget above assumes 2.4e-7.
    x = np.linspace(0.0, 80.0, 200_001, dtype=np.float32)
    exact = np.exp(-x.astype(np.float64))
    np.testing.assert_allclose(_exp_neg_of(x), exact, rtol=2.4e-7, atol=0)
