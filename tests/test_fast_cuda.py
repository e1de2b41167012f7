"""Equivalence of kintinuous_fast's CUDA kernels with kintinuous_ref, on a GPU or on numba's CUDA
simulator.

Without a GPU these tests are skipped in the main pytest process and run instead in a child
process with NUMBA_ENABLE_CUDASIM=1 (tests/test_fast_backends.py starts it: the simulator must
be switched on before numba is imported). The simulator runs every CUDA thread as a Python
thread, about 10^4 times slower than a CPU loop, so its frames are tiny (32x24; kernels with
barriers about 80x60) and the bilateral window is 7x7; on a GPU the sizes of the CPU tests are
used. Cases and tolerances: tests/fast_equivalence.py.
"""

import fast_equivalence as fe
import numpy as np
import pytest

from kintinuous_fast import cuda_is_simulated, cuda_status
from kintinuous_ref import preprocess as ref
from kintinuous_ref.config import PreprocessConfig, VolumeConfig

pytestmark = pytest.mark.skipif(
    bool(cuda_status()),
    reason="no CUDA GPU: runs in the simulator subprocess of test_fast_backends.py",
)

SIMULATED = cuda_is_simulated()
fe.QUICK = SIMULATED
SIZES = [(24, 32)] if SIMULATED else [(60, 80), (120, 160)]
RADIUS = 3 if SIMULATED else 6
SIM_CONFIG = PreprocessConfig(bilateral_radius=RADIUS, pyramid_levels=3)


@pytest.fixture(autouse=True)
def gpu_rounding(monkeypatch):
    # fused multiply-adds on real hardware (fast_equivalence.CONTRACTED), for these tests only
    monkeypatch.setattr(fe, "CONTRACTED", not SIMULATED)


@pytest.fixture(scope="module")
def gpu():
    from kintinuous_fast.preprocess import cuda as preprocess

    return preprocess


@pytest.mark.parametrize("size", SIZES, ids=lambda s: f"{s[1]}x{s[0]}")
@pytest.mark.parametrize(
    "check",
    [
        fe.check_metric_depth,
        fe.check_pyramid_down,
        fe.check_vertex_normal_maps,
        fe.check_intensity,
        fe.check_discontinuity_mask,
    ],
    ids=lambda check: check.__name__.removeprefix("check_"),
)
def test_equivalence_cuda_preprocess(gpu, check, size):
    check(gpu, *size)


@pytest.mark.parametrize("size", SIZES, ids=lambda s: f"{s[1]}x{s[0]}")
def test_equivalence_cuda_preprocess_bilateral_filter(gpu, size):
    fe.check_bilateral_filter(gpu, *size, radius=RADIUS)


def test_equivalence_cuda_preprocess_frame_host_arrays(gpu):
    # NumPy images in, NumPy frame out (uploaded once, downloaded at the end). On the simulator
    # a 24x16 frame with 2 levels; the device-array test below covers the stages at full size.
    if SIMULATED:
        fe.check_preprocess_frame(
            gpu, 16, 24, PreprocessConfig(bilateral_radius=2, pyramid_levels=2)
        )
    else:
        for size in SIZES:
            fe.check_preprocess_frame(gpu, *size)


def test_equivalence_cuda_preprocess_frame_on_device(gpu):
    # Device images in: every array of the frame is a device array, equal to the reference.
    from numba import cuda

    from kintinuous_fast.targets.cuda import is_device

    height, width = SIZES[-1]
    config = SIM_CONFIG if SIMULATED else PreprocessConfig()
    camera = fe.camera_for(height, width)
    colour, depth = fe.scene_colour(height, width), fe.raw_depth(height, width)
    frame = gpu.preprocess_frame(cuda.to_device(colour), cuda.to_device(depth), camera, config)
    arrays = [frame.colour, frame.depth, frame.colour_mask]
    for level in frame.levels:
        arrays += [level.depth, level.vertices, level.normals, level.intensity]
        arrays += [level.intensity_dx, level.intensity_dy]
    assert all(is_device(array) for array in arrays)
    fe.compare_frames(gpu.frame_to_host(frame), ref.preprocess_frame(colour, depth, camera, config))
    # model_pyramid subsamples device maps without a copy to the host
    pyramid = gpu.model_pyramid(frame.levels[0].vertices, frame.levels[0].normals, 2)
    assert is_device(pyramid[1][0])
    np.testing.assert_array_equal(
        pyramid[1][0].copy_to_host(), frame.levels[0].vertices.copy_to_host()[::2, ::2]
    )


# ----------------------------------------------------------------------------------------------
# TSDF + colour integration, sampling and raycasting (the "volume" stage)

VOLUME_SIZES = [(24, 32, 16)] if SIMULATED else [(60, 80, 32), (120, 160, 48)]


@pytest.fixture(scope="module")
def gpu_volume():
    from kintinuous_fast.raycast import cuda as raycast
    from kintinuous_fast.tsdf import cuda as tsdf

    return tsdf, raycast


@pytest.mark.parametrize("size", VOLUME_SIZES, ids=lambda s: f"{s[1]}x{s[0]}-{s[2]}^3")
def test_equivalence_cuda_volume_integrate(gpu_volume, size):
    fe.check_integrate(gpu_volume[0], *size)


def test_equivalence_cuda_volume_integrate_weighted_colour(gpu_volume):
    fe.check_integrate_weighted_colour(gpu_volume[0], *VOLUME_SIZES[0])


def test_equivalence_cuda_volume_integrate_degenerate(gpu_volume):
    fe.check_integrate_degenerate(gpu_volume[0], *VOLUME_SIZES[0][:2])


@pytest.mark.filterwarnings("ignore:invalid value encountered in cast")  # ref, NaN input
def test_equivalence_cuda_volume_sample_tsdf(gpu_volume):
    fe.check_sample_tsdf(gpu_volume[0], *VOLUME_SIZES[0])


@pytest.mark.parametrize("size", VOLUME_SIZES, ids=lambda s: f"{s[1]}x{s[0]}-{s[2]}^3")
def test_equivalence_cuda_volume_raycast(gpu_volume, size):
    fe.check_raycast(*gpu_volume, *size)


def test_equivalence_cuda_volume_empty_space(gpu_volume):
    """The raycast's brick distance map, computed on the device, is the reference's
    (kintinuous_ref.raycast.empty_space, scipy's distance transform) exactly: for a fused
    volume, for two negative voxels far apart in a 48^3 volume (distances up to 4 bricks),
    with the cyclical buffer at rest and wrapped, and for an empty volume (2 B everywhere)."""
    from numba import cuda

    from kintinuous_fast.tsdf.volume import FastTsdfVolume, to_reference_volume
    from kintinuous_ref import raycast as ref_raycast

    tsdf, raycast = gpu_volume
    height, width, _ = VOLUME_SIZES[0]
    fused, _ = fe.fused_volumes(tsdf, height, width, 32, 1, weighted=False)
    packed = np.zeros((48, 48, 48, 2), dtype=np.int16)
    packed[3, 40, 20] = packed[30, 5, 44] = (-100, 1)
    packed[10, 10, 10] = (-100, 0)  # unobserved: not a surface
    sparse = FastTsdfVolume(cuda.to_device(packed), None, np.zeros(3), 0.01, 0.03, 128.0)
    for volume in (fused, sparse):
        for offset in ((0, 0, 0), (5, 0, 27)):
            volume.offset = np.array(offset)
            want = ref_raycast.empty_space(to_reference_volume(volume))
            np.testing.assert_array_equal(raycast.empty_space(volume).copy_to_host(), want)
    assert want.min() == 0 and want.max() == 4  # the separable passes met long distances too
    empty = tsdf.make_volume(VolumeConfig(resolution=32, size=3.0), np.eye(4))
    np.testing.assert_array_equal(raycast.empty_space(empty).copy_to_host(), np.full((4,) * 3, 8))
    # The raycast's jumps over empty bricks return the plain march's maps bit for bit.
    fused.offset = np.zeros(3, dtype=np.int64)
    assert ref_raycast.empty_space(to_reference_volume(fused)).max() >= 1
    camera, view = fe.camera_for(height, width), fe.moving_poses(2)[1]
    skipping = raycast.raycast(fused, view, camera)
    plain = raycast.raycast(fused, view, camera, skip_empty=False)
    assert np.isfinite(plain.vertices).mean() > 0.3
    np.testing.assert_array_equal(skipping.vertices, plain.vertices)
    np.testing.assert_array_equal(skipping.normals, plain.normals)


def test_equivalence_cuda_volume_stays_on_device(gpu_volume):
    from kintinuous_fast.targets.cuda import is_device

    tsdf, raycast = gpu_volume
    height, width, resolution = VOLUME_SIZES[0]
    volume, _ = fe.fused_volumes(tsdf, height, width, resolution, 1, weighted=False)
    assert is_device(volume.tsdf_weight) and is_device(volume.colour)
    prediction = raycast.predict_surface(volume, np.eye(4), fe.camera_for(height, width))
    assert is_device(prediction.vertices) and is_device(prediction.normals)


def test_equivalence_cuda_volume_integrate_bounded_on_the_device(gpu_volume):
    """integrate bounds the frustum by the volume's reach and each voxel column by the frame's
    largest depth, read on the device (no download). On frames far nearer than the volume
    reaches, with colour, the volume is voxel for voxel the one that fusing every voxel of the
    frustum box of the frame's largest depth (computed on the host) gives."""
    from numba import cuda

    from kintinuous_fast.tsdf.volume import frustum_box

    tsdf, _ = gpu_volume
    height, width, resolution = VOLUME_SIZES[0]
    camera = fe.camera_for(height, width)
    config = VolumeConfig(resolution=resolution, size=3.0)
    poses = fe.moving_poses(2)
    bounded, whole = (tsdf.make_volume(config, poses[0]) for _ in range(2))
    colour = fe.scene_colour(height, width)
    for index, pose in enumerate(poses):
        depth = np.float32(0.4) * fe.scene_depth(height, width, seed=index)  # 0.6 to 1.2 m
        nearest_box = frustum_box(whole, float(depth.max()), pose, camera)
        reach = tsdf.volume_reach(whole, pose)
        reach_box = frustum_box(whole, reach, pose, camera)
        assert reach > 2.0 * depth.max()
        assert np.prod(reach_box[1] - reach_box[0]) > 2 * np.prod(nearest_box[1] - nearest_box[0])
        tsdf.integrate(bounded, depth, pose, camera, colour)
        tsdf.integrate_in_box(whole, cuda.to_device(depth), pose, camera, colour, None, nearest_box)
    want = whole.tsdf_weight.copy_to_host()
    assert np.count_nonzero(want[..., 1]) > 0.02 * resolution**3  # a real test
    np.testing.assert_array_equal(bounded.tsdf_weight.copy_to_host(), want)
    np.testing.assert_array_equal(bounded.colour.copy_to_host(), whole.colour.copy_to_host())


def test_cuda_volume_and_frame_stages_copy_nothing_after_the_first_frame(
    gpu, gpu_volume, monkeypatch
):
    """Preprocessing device images, colour weights, integration (with and without colour
    weights) and the surface prediction: after a first frame, a frame copies nothing between
    host and device (each such copy waits for the device's queued work). Constant tables stay
    on the device; per-frame values go as launch parameters. (Named for the simulator's
    "volume" child.)"""
    from numba import cuda

    from kintinuous_fast.colour import cuda as colour
    from kintinuous_ref.config import ColourConfig

    if SIMULATED:
        from numba.cuda.simulator.cudadrv.devicearray import FakeCUDAArray as device_array
    else:
        from numba.cuda.cudadrv.devicearray import DeviceNDArrayBase as device_array
    tsdf, raycast = gpu_volume
    height, width, resolution = (16, 24, 16) if SIMULATED else VOLUME_SIZES[0]
    camera = fe.camera_for(height, width)
    config = PreprocessConfig(bilateral_radius=2, pyramid_levels=2)
    poses = fe.moving_poses(2)
    volume = tsdf.make_volume(VolumeConfig(resolution=resolution, size=3.0), poses[0])
    images = [
        (
            cuda.to_device(fe.scene_colour(height, width, seed)),
            cuda.to_device(fe.raw_depth(height, width, seed)),
        )
        for seed in range(2)
    ]

    def one_frame(index: int) -> None:
        frame = gpu.preprocess_frame(*images[index], camera, config)
        weights = colour.colour_weights(frame, ColourConfig())
        tsdf.integrate(volume, frame.depth, poses[index], camera, frame.colour, weights)
        tsdf.integrate(volume, frame.depth, poses[index], camera, frame.colour)
        tsdf.integrate(volume, frame.depth, poses[index], camera)
        raycast.predict_surface(volume, poses[index], camera, stride=2)

    one_frame(0)
    crossings: list[str] = []
    upload, download = cuda.to_device, device_array.copy_to_host

    def counted_upload(*args, **kwargs):  # noqa: ANN002, ANN003, ANN202
        crossings.append("up")
        return upload(*args, **kwargs)

    def counted_download(*args, **kwargs):  # noqa: ANN002, ANN003, ANN202
        crossings.append("down")
        return download(*args, **kwargs)

    monkeypatch.setattr(cuda, "to_device", counted_upload)
    monkeypatch.setattr(device_array, "copy_to_host", counted_download)
    one_frame(1)
    assert crossings == []


def test_equivalence_cuda_volume_offset_and_origin_read_on_the_device():
    """The moving volume's buffer offset and origin reach integration and the raycast through
    device memory (tsdf.cuda.volume_placement): at an offset that wraps along x and z, with the
    origin away from the first pose, the volume and the raycast equal the reference's; then a
    new offset and origin (what a shift sets) are read by the next raycast without anything
    else changing, so it again equals the reference's on the same cells."""
    from kintinuous_fast.raycast import cuda as cuda_raycast
    from kintinuous_fast.tsdf import cuda as cuda_tsdf
    from kintinuous_fast.tsdf.volume import to_reference_volume
    from kintinuous_ref import raycast as ref_raycast
    from kintinuous_ref import tsdf as ref_tsdf

    height, width, n = (24, 32, 16) if SIMULATED else (60, 80, 32)
    config = VolumeConfig(resolution=n, size=3.0)
    camera, poses = fe.camera_for(height, width), fe.moving_poses(2)
    reference = ref_tsdf.make_volume(config, poses[0])
    fast = cuda_tsdf.make_volume(config, poses[0])
    for volume in (reference, fast):
        volume.offset[:] = (5, 0, n - 5)
    for index, pose in enumerate(poses):
        depth = fe.scene_depth(height, width, seed=index)
        ref_tsdf.integrate(reference, depth, pose, camera)
        cuda_tsdf.integrate(fast, depth, pose, camera)
    back = to_reference_volume(fast)
    np.testing.assert_array_equal(back.weight, reference.weight)
    np.testing.assert_allclose(back.tsdf, reference.tsdf, atol=len(poses) * 0.5 / 32767 + 1e-7)
    assert np.count_nonzero(reference.weight) > 0.02 * reference.weight.size  # a real test
    for shifted in (False, True):
        if shifted:  # the same cells seen as another part of the world
            fast.offset[:] = (2, 7, 1)
            fast.origin = fast.origin + np.array([0.02, -0.01, 0.03])
            back = to_reference_volume(fast)
        got = cuda_raycast.raycast(fast, poses[1], camera)
        want = ref_raycast.raycast(back, poses[1], camera)
        hit_got, hit_want = ~np.isnan(got.vertices[..., 0]), ~np.isnan(want.vertices[..., 0])
        assert hit_want.mean() > 0.2
        assert np.count_nonzero(hit_got != hit_want) <= 0.002 * hit_want.size + 1
        both = hit_got & hit_want
        np.testing.assert_allclose(got.vertices[both], want.vertices[both], atol=1e-5, rtol=0)
