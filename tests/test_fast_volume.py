"""Equivalence of kintinuous_fast's CPU TSDF + colour integration, TSDF sampling and raycasting
with kintinuous_ref (tsdf.py, raycast.py) on small frames and volumes. Cases and tolerances
(int16 TSDF, uint8 colour) are in tests/fast_equivalence.py; the CUDA twin is test_fast_cuda.py.
"""

import fast_equivalence as fe
import numpy as np
import pytest

from kintinuous_fast.raycast import cpu as cpu_raycast
from kintinuous_fast.targets import cpu_jit
from kintinuous_fast.tsdf import cpu as cpu_tsdf
from kintinuous_fast.tsdf import cpu_culling
from kintinuous_fast.tsdf import volume as _volume
from kintinuous_fast.tsdf import voxel as volume_ops
from kintinuous_ref import tsdf as ref_tsdf
from kintinuous_ref.config import VolumeConfig
from kintinuous_ref.errors import ConfigError

SIZES = [(60, 80, 32), (120, 160, 48)]
IDS = ["80x60-32^3", "160x120-48^3"]


@pytest.mark.parametrize("size", SIZES, ids=IDS)
def test_equivalence_cpu_integrate(size):
    fe.check_integrate(cpu_tsdf, *size)


def test_equivalence_cpu_integrate_weighted_colour():
    fe.check_integrate_weighted_colour(cpu_tsdf, 60, 80, 32)


def test_equivalence_cpu_integrate_degenerate():
    fe.check_integrate_degenerate(cpu_tsdf, 60, 80)


@pytest.mark.filterwarnings("ignore:invalid value encountered in cast")  # ref, NaN input
def test_equivalence_cpu_sample_tsdf():
    fe.check_sample_tsdf(cpu_tsdf, 60, 80, 32)


@pytest.mark.parametrize("size", SIZES, ids=IDS)
def test_equivalence_cpu_raycast(size):
    fe.check_raycast(cpu_tsdf, cpu_raycast, *size)


@pytest.mark.parametrize(("rows", "threads"), [(480, 16), (480, 2), (240, 7), (61, 1), (1, 4)])
def test_raycast_bands_shrink_to_the_least_and_cover_every_row_once(rows, threads):
    """_band_starts: bands in order from row 0 to the last, the first a 2 * threads-th of the
    rows, then never larger, none but the last under MIN_BAND rows."""
    starts = cpu_raycast._band_starts(rows, threads)
    sizes = np.diff(starts)
    assert starts[0] == 0 and starts[-1] == rows and (sizes > 0).all()
    assert sizes[0] == min(rows, max(cpu_raycast.MIN_BAND, rows // (2 * threads)))
    assert (np.diff(sizes) <= 0).all() and (sizes[:-1] >= cpu_raycast.MIN_BAND).all()


@pytest.mark.parametrize("holes", ["zeros", "nan", "negative", "all holes"])
def test_the_largest_depth_is_the_largest_positive_one(holes):
    """integrate's far limit: _largest_depth equals NumPy's depth[depth > 0].max(), and 0 with no
    positive depth; NaN and negative depths are holes."""
    rng = np.random.default_rng(7)
    depth = (rng.random((120, 160)) * 4.0).astype(np.float32)
    hole = {"zeros": 0.0, "nan": np.nan, "negative": -5.0, "all holes": np.nan}[holes]
    depth[rng.random(depth.shape) < (1.0 if holes == "all holes" else 0.3)] = hole
    positive = depth[depth > 0]
    expected = float(positive.max()) if positive.size else 0.0
    assert float(cpu_tsdf._largest_depth(depth)) == expected
    assert holes != "all holes" or expected == 0.0


@pytest.mark.parametrize("offset", [(0, 0, 0), (5, 0, 17)], ids=["fixed", "shifted"])
def test_equivalence_cpu_gradient_normal(offset):
    """tsdf.voxel.gradient_normal against kintinuous_ref.raycast._gradient_normals on a fused
    volume, plain and as a shifted cyclical buffer, at points inside (one blend of stored
    differences) and on and next to the one-voxel border (six clipped samples).

    Tolerance 5e-7 / |g| per component, g the reference's gradient: it rounds each of its six
    samples to float32 (half an ulp of F ~ 1 is 6e-8) before differencing, so each component
    of g carries up to 1.2e-7 of rounding, and a unit normal 1.2e-7 * sqrt(3) * 2 / |g|.
    At a surface |g| is ~0.8 (F falls by 2 voxels / truncation per 2 voxels): 6e-7. Where g
    is within its rounding of zero (<= 1e-5) there is no direction to compare. Where it is
    exactly 0 (unobserved space, flat TSDF) the normal is NaN, but at a few points a hair
    from the border, where the fraction is 1 - 1e-12 and the blend keeps a 1e-12 share of a
    difference that the reference's rounding drops."""
    from kintinuous_ref.raycast import _gradient_normals

    fast, _ = fe.fused_volumes(cpu_tsdf, 60, 80, 32, 2, weighted=False)
    n = fast.resolution
    fast.tsdf_weight = np.roll(fast.tsdf_weight, offset, axis=(0, 1, 2))
    fast.offset = np.array(offset, dtype=np.int64)
    reference = _volume.to_reference_volume(fast)
    rng = np.random.default_rng(3)
    inside = rng.uniform(0.0, n - 1.0, (4000, 3))
    edges = np.array([0.0, 0.4, 1.0 - 1e-12, 1.0, n - 2.0 - 1e-12, n - 2.0, n - 1.5, n - 1.0])
    border = inside[:2000].copy()
    border[np.arange(2000), rng.integers(0, 3, 2000)] = rng.choice(edges, 2000)
    coordinates = np.concatenate([inside, border])
    gradient_normal = volume_ops.build_ops(cpu_jit).gradient_normal
    got = np.array([gradient_normal(fast.tsdf_weight, *fast.offsets(), *c) for c in coordinates])
    want = _gradient_normals(reference, reference.voxel_to_world(coordinates))
    length = np.linalg.norm(reference_gradient(reference, coordinates), axis=-1)
    defined = length > 1e-5
    assert defined.mean() > 0.2  # a quarter of the box sees a gradient (the rest: unobserved)
    error = np.abs(got[defined] - want[defined]).max(axis=-1)
    assert (error <= 5e-7 / length[defined]).all(), error.max()
    flat = length == 0
    assert np.isnan(got[flat]).all(axis=-1).mean() > 0.995


def reference_gradient(volume: ref_tsdf.TsdfVolume, coordinates: np.ndarray) -> np.ndarray:
    """The TSDF gradient that kintinuous_ref.raycast._gradient_normals normalises."""
    limit = volume.resolution - 1
    return np.stack(
        [
            ref_tsdf.trilinear(volume.tsdf, np.clip(coordinates + e, 0, limit), volume.offset)
            - ref_tsdf.trilinear(volume.tsdf, np.clip(coordinates - e, 0, limit), volume.offset)
            for e in np.eye(3)
        ],
        axis=-1,
    )


def test_fast_volume_is_eight_bytes_per_voxel_and_round_trips():
    config = VolumeConfig(resolution=512, size=6.0)
    assert _volume.memory_bytes(config) == 2**30  # the paper's 512^3 in 1 GiB
    assert ref_tsdf.memory_bytes(config) == 3 * 2**30
    reference, _ = fe.fused_volumes(cpu_tsdf, 60, 80, 32, 1, weighted=False)
    back = _volume.to_reference_volume(reference)
    again = _volume.to_reference_volume(_volume.from_reference_volume(back))
    np.testing.assert_array_equal(again.tsdf, back.tsdf)
    np.testing.assert_array_equal(again.colour, back.colour)


def test_fast_make_volume_refuses_what_cannot_fit(monkeypatch):
    with pytest.raises(ConfigError, match="needs .* GiB but only"):
        _volume.check_volume_memory(VolumeConfig(resolution=1024), available=2**30)
    monkeypatch.setattr(_volume, "available_memory_bytes", lambda: 2**30)
    with pytest.raises(ConfigError, match=r"needs 8\.0 GiB but only 1\.0 GiB"):
        cpu_tsdf.make_volume(VolumeConfig(resolution=1024), np.eye(4))


def test_each_backend_checks_its_own_volume_against_its_own_memory(monkeypatch):
    """512^3 with colour and 2.5 GiB of host memory free: the fast volume (8 bytes per voxel,
    1.0 GiB) fits, the reference's (24 bytes, 3.0 GiB) does not; the cuda volume is checked
    against the GPU's free memory whatever the host has."""
    from numba import cuda

    from kintinuous_fast.tsdf import cuda as cuda_tsdf

    config = VolumeConfig(resolution=512, size=6.0)
    monkeypatch.setattr(ref_tsdf, "available_memory_bytes", lambda: 5 << 29)
    monkeypatch.setattr(_volume, "available_memory_bytes", lambda: 5 << 29)
    cpu_tsdf.check_volume_config(config)
    with pytest.raises(ConfigError, match=r"needs 3\.0 GiB but only 2\.5 GiB"):
        ref_tsdf.check_volume_config(config)

    class Context:  # a GPU with 0.5 GiB free
        def get_memory_info(self) -> tuple[int, int]:
            return 1 << 29, 80 << 30

    monkeypatch.setattr(cuda, "current_context", Context)
    monkeypatch.setattr(_volume, "available_memory_bytes", lambda: 64 << 30)
    assert cuda_tsdf.available_memory_bytes() == 1 << 29
    with pytest.raises(ConfigError, match=r"needs 1\.0 GiB but only 0\.5 GiB"):
        cuda_tsdf.check_volume_config(config)


@pytest.mark.parametrize("table", [False, True], ids=["arithmetic", "table"])
def test_dequantise_is_the_float32_division_for_every_int16(table):
    """tsdf.voxel.dequantise multiplies in float64 instead of dividing in float32 (cuda), or
    reads a table made so (cpu); the result must be the correctly rounded q / 32767
    (to_reference_volume's) for every stored value."""
    dequantise = volume_ops.build_ops(cpu_jit, dequantise_table=table).dequantise
    q = np.arange(-32767, 32768, dtype=np.int16)
    got = np.array([dequantise(value) for value in q], dtype=np.float32)
    np.testing.assert_array_equal(got, q.astype(np.float32) / np.float32(32767.0))


def test_rint32_is_np_rint_over_the_image_range():
    """ops.build_rint's rint32 (project_voxel's rounding: np.rint has no CUDA lowering) adds and
    subtracts 1.5 * 2^23 in float32; it must equal np.rint, ties to even, for every pixel
    coordinate a projection can keep: ties, their neighbours, random values."""
    rint32 = cpu_tsdf._ops.rint32
    halves = np.arange(-8, 2 * 1300, dtype=np.float32) / np.float32(2.0)
    rng = np.random.default_rng(7)
    values = np.concatenate(
        [
            halves,
            np.nextafter(halves, np.float32(np.inf)),
            np.nextafter(halves, np.float32(-np.inf)),
            rng.uniform(-4.0, 1300.0, 20000).astype(np.float32),
        ]
    )
    got = np.array([rint32(value) for value in values], dtype=np.float32)
    np.testing.assert_array_equal(got, np.rint(values))


@pytest.mark.parametrize("angle", [True, False], ids=["angle", "no-angle"])
@pytest.mark.parametrize("check", [True, False], ids=["edges", "no-edges"])
def test_equivalence_cpu_colour_weights(angle, check):
    """The cpu loop's colour weights are the reference's bit for bit (0, 1 or |n_z| products)
    on a frame with holes, NaN normals and depth edges."""
    from kintinuous_fast.colour import cpu as cpu_colour
    from kintinuous_ref import preprocess
    from kintinuous_ref.colour import colour_weights
    from kintinuous_ref.config import ColourConfig, PreprocessConfig
    from kintinuous_ref.datasets.synthetic import make_scenario

    desk = make_scenario("desk", frames=2, width=160, height=120)
    rgb, depth = desk.render(1)
    depth[40:50, 60:80] = 0.0  # a hole
    frame = preprocess.preprocess_frame(rgb, depth, desk.camera, PreprocessConfig())
    assert np.isnan(frame.levels[0].normals).any() and (frame.depth == 0).any()
    assert not frame.colour_mask.all()
    config = ColourConfig(angle_weighting=angle, discontinuity_check=check)
    got = cpu_colour.colour_weights(frame, config)
    assert got.dtype == np.float32
    np.testing.assert_array_equal(got, colour_weights(frame, config))


@pytest.mark.parametrize("pose_index", [0, 3], ids=["facing", "turned"])
def test_cpu_integration_visits_every_voxel_the_reference_updates(pose_index):
    """The column ranges cpu integration visits (cpu.tsdf._columns_to_visit: bricks that may
    hold an update, from a max pyramid of lambda D) hold every voxel that the reference's
    integration of the frame updates, and leave out a real share of the frustum's voxels
    (those far behind the wall)."""
    from kintinuous_fast.tsdf.volume import camera_frame_steps, frustum_box

    height, width, n = 120, 160, 64
    camera = fe.camera_for(height, width)
    config = VolumeConfig(resolution=n, size=4.0)
    pose = fe.moving_poses(4)[pose_index]
    depth = fe.scene_depth(height, width, seed=pose_index)
    reference = ref_tsdf.make_volume(config, fe.moving_poses(1)[0])
    ref_tsdf.integrate(reference, depth, pose, camera)
    updated = np.argwhere(reference.weight > 0)
    assert len(updated) > 0.05 * n**3  # a real test

    fast = cpu_tsdf.make_volume(config, fe.moving_poses(1)[0])
    box = frustum_box(fast, float(depth.max()), pose, camera)
    ray_distance = cpu_tsdf.ray_distances(depth.astype(np.float32), camera)
    base, steps = camera_frame_steps(fast, pose)
    visit = cpu_culling.columns_to_visit(fast, box, base, steps, camera, ray_distance, pose)
    sizes = cpu_culling.CULL_BRICK
    bundle = visit[updated[:, 0] // sizes[0], updated[:, 1] // sizes[1]]
    assert np.all((bundle[:, 0] <= updated[:, 2]) & (updated[:, 2] < bundle[:, 1]))
    i, j = np.mgrid[box[0][0] : box[1][0], box[0][1] : box[1][1]]
    columns = visit[i // sizes[0], j // sizes[1]]
    visited = np.maximum(columns[..., 1] - columns[..., 0], 0).sum()
    assert visited < 0.8 * np.prod(box[1] - box[0])
