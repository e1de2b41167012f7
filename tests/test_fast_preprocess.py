"""Equivalence of kintinuous_fast's CPU preprocessing with kintinuous_ref.preprocess on small
frames (80x60 and 160x120) with holes, borders, depth edges, junk values and empty maps.
The cases and their tolerances are in tests/fast_equivalence.py; the CUDA twin of this file is
tests/test_fast_cuda.py."""

import fast_equivalence as fe
import numpy as np
import pytest

from kintinuous_fast.cpu import preprocess as cpu
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
