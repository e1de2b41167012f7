"""The host-side helpers of kintinuous_fast that set up kernel arguments (launch grids, chunks,
per-call constants, input checks), each against a closed form or the reference's own maths. The
kernels they feed are checked against the reference in the equivalence tests."""

import numpy as np
import pytest

from kintinuous_fast.odometry import check_image, check_map
from kintinuous_fast.odometry.icp import icp_constants, kernel_code
from kintinuous_fast.odometry.sums import chunks_for
from kintinuous_fast.preprocess.host import gaussian3x3, inverse_two_variance
from kintinuous_fast.targets.cuda import grid_1d, grid_2d
from kintinuous_fast.tsdf.cpu import make_volume
from kintinuous_fast.tsdf.volume import fusion_limits, image_size, index_box
from kintinuous_ref import se3
from kintinuous_ref.camera import Intrinsics
from kintinuous_ref.config import VolumeConfig
from kintinuous_ref.errors import ConfigError, DatasetError
from kintinuous_ref.odometry.icp import ROBUST_KERNELS
from kintinuous_ref.preprocess import _gaussian3x3 as ref_gaussian3x3

CAMERA = Intrinsics(500.0, 500.0, 319.5, 239.5, 640, 480)


def test_launch_grids_cover_every_item_with_the_fewest_blocks():
    assert [grid_1d(n, 128) for n in (0, 1, 128, 129, 300)] == [1, 1, 1, 2, 3]
    assert grid_2d(480, 640, (16, 16)) == (40, 30)  # (blocks along x = columns, along y)
    assert grid_2d(481, 641, (16, 16)) == (41, 31)
    assert chunks_for(0, 8) == 1 and chunks_for(5, 8) == 5 and chunks_for(99, 8) == 8


def test_icp_constants_are_the_reference_association_terms():
    pose = se3.exp(np.array([0.01, -0.02, 0.03, 0.1, 0.2, -0.1]))
    model_pose = se3.exp(np.array([-0.03, 0.01, 0.02, 0.0, -0.1, 0.3]))
    got_pose, to_model, dist2, cos_min = icp_constants(pose, model_pose, 0.1, 20.0)
    np.testing.assert_array_equal(got_pose, pose)
    np.testing.assert_allclose(to_model, np.linalg.inv(model_pose) @ pose, atol=1e-15)
    assert dist2 == pytest.approx(0.01) and cos_min == pytest.approx(np.cos(np.pi / 9))


def test_robust_kernel_codes_and_the_one_line_error():
    assert [kernel_code(name) for name in ROBUST_KERNELS] == list(range(len(ROBUST_KERNELS)))
    with pytest.raises(ConfigError, match="icp.robust_kernel must be one of") as error:
        kernel_code("cauchy")
    assert "\n" not in str(error.value)


def test_map_and_image_checks_name_both_shapes_in_one_line():
    check_map("model vertex map", np.zeros((480, 640, 3)), CAMERA)
    check_image("depth", np.zeros((30, 40)), (30, 40))
    with pytest.raises(DatasetError, match=r"\(240, 320, 3\), expected \(480, 640, 3\)"):
        check_map("model vertex map", np.zeros((240, 320, 3)), CAMERA)
    with pytest.raises(DatasetError, match=r"depth is \(30, 41\), expected \(30, 40\)"):
        check_image("depth", np.zeros((30, 41)), (30, 40))


def test_preprocessing_constants_match_the_reference():
    np.testing.assert_allclose(gaussian3x3(0.8), ref_gaussian3x3(0.8), rtol=0, atol=1e-17)
    assert gaussian3x3(0.8).sum() == pytest.approx(1.0, abs=1e-15)
    assert inverse_two_variance(0.03) == np.float32(1.0 / (2.0 * 0.03**2))


def test_volume_kernel_arguments():
    volume = make_volume(VolumeConfig(resolution=32, size=1.0), np.eye(4), 128.0)
    assert fusion_limits(volume) == (
        np.float32(volume.truncation),
        np.float32(volume.max_weight),
        np.float32(128.0),
    )
    assert image_size(CAMERA) == (640, 480)
    assert index_box((np.array([1, 2, 3]), np.array([4, 5, 6]))) == ((1, 2, 3), (4, 5, 6))


def test_fovis_reads_a_host_frame_as_it_is():
    from kintinuous_fast.odometry.cuda import fovis_images
    from kintinuous_ref.config import PreprocessConfig
    from kintinuous_ref.preprocess import preprocess_frame

    depth = np.full((30, 40), 7500, np.uint16)  # 1.5 m in TUM units
    colour = np.zeros((30, 40, 3), np.uint8)
    camera = Intrinsics(40.0, 40.0, 19.5, 14.5, 40, 30)
    frame = preprocess_frame(colour, depth, camera, PreprocessConfig())
    assert fovis_images(frame) is frame
