"""The fast backends' cyclical buffer (moving volume, paper III) against kintinuous_ref: the same
offset gives the same integration, sampling and raycast, and kintinuous_ref.moving_volume's
shifts, slice extraction and clearing on a fast volume (through
kintinuous_fast.tsdf.volume.SlabView) give the reference's slices and volume. Tolerances are
those of tests/fast_equivalence.py (int16 TSDF: 0.5 / 32767 per frame; uint8 colour: 0.5 level
per frame)."""

import fast_equivalence as fe
import numpy as np
import pytest

from kintinuous_fast.raycast import cpu as cpu_raycast
from kintinuous_fast.raycast import cpu_near_starts, cpu_ops, cpu_skip_maps
from kintinuous_fast.tsdf import cpu as cpu_tsdf
from kintinuous_fast.tsdf.volume import (
    FastTsdfVolume,
    from_reference_volume,
    slab_view,
    to_reference_volume,
)
from kintinuous_fast.tsdf.voxel import FINE
from kintinuous_ref import raycast as ref_raycast
from kintinuous_ref import tsdf as ref_tsdf
from kintinuous_ref.config import VolumeConfig
from kintinuous_ref.moving_volume import MovingVolume
from kintinuous_ref.raycast import STEP_FRACTION

HEIGHT, WIDTH, N = 60, 80, 32
CONFIG = VolumeConfig(resolution=N, size=3.0, shift_threshold=2, min_extract_weight=1.0)
OFFSET = np.array([5, 0, 27])  # wraps along x and z, none along y


def assert_same_volume(fast, reference, frames: int) -> None:
    back = to_reference_volume(fast)
    np.testing.assert_array_equal(back.offset, reference.offset)
    np.testing.assert_array_equal(back.weight, reference.weight)
    np.testing.assert_allclose(back.tsdf, reference.tsdf, atol=0.5 * frames / 32767 + 1e-7)
    np.testing.assert_array_equal(back.colour_weight, reference.colour_weight)
    coloured = reference.colour_weight > 0
    np.testing.assert_allclose(back.colour[coloured], reference.colour[coloured], atol=0.5 * frames)


def test_equivalence_cpu_offset_integrate_sample_raycast():
    camera = fe.camera_for(HEIGHT, WIDTH)
    poses = fe.moving_poses(2)
    reference = ref_tsdf.make_volume(CONFIG, poses[0])
    reference.offset[:] = OFFSET
    fast = cpu_tsdf.make_volume(CONFIG, poses[0])
    fast.offset[:] = OFFSET
    colour = fe.scene_colour(HEIGHT, WIDTH)
    for index, pose in enumerate(poses):
        depth = fe.scene_depth(HEIGHT, WIDTH, seed=index)
        ref_tsdf.integrate(reference, depth, pose, camera, colour)
        cpu_tsdf.integrate(fast, depth, pose, camera, colour)
    assert np.count_nonzero(reference.weight) > 0.02 * reference.weight.size  # a real test
    # The cells really wrapped: the same data at zero offset lands elsewhere in the arrays.
    assert np.any(reference.weight != np.roll(reference.weight, tuple(-OFFSET), axis=(0, 1, 2)))
    assert_same_volume(fast, reference, len(poses))

    back = to_reference_volume(fast)  # same values: sampling and raycasting must agree
    rng = np.random.default_rng(5)
    coordinates = rng.uniform(-0.5, N - 0.5, (400, 3))
    np.testing.assert_allclose(
        cpu_tsdf.sample_tsdf(fast, coordinates),
        ref_tsdf.sample_tsdf(back, coordinates),
        atol=fe.SAMPLE_TSDF_ATOL,
        rtol=0,
    )
    for pose in poses:
        got = cpu_raycast.raycast(fast, pose, camera)
        want = ref_raycast.raycast(back, pose, camera)
        hit_got, hit_want = ~np.isnan(got.vertices[..., 0]), ~np.isnan(want.vertices[..., 0])
        assert hit_want.mean() > 0.3
        assert np.count_nonzero(hit_got != hit_want) <= 0.002 * hit_want.size
        both = hit_got & hit_want
        np.testing.assert_allclose(got.vertices[both], want.vertices[both], atol=1e-5, rtol=0)
        np.testing.assert_allclose(got.normals[both], want.normals[both], atol=1e-5, rtol=0)
        assert np.abs(got.colours[both].astype(int) - want.colours[both]).max() <= 1


@pytest.mark.parametrize("plain", [False, True], ids=["skipping", "plain-march"])
def test_equivalence_cpu_raycast_skipping_is_exact(plain):
    # The brick skipping returns the plain march's answer (kintinuous_ref.raycast.march).
    camera = fe.camera_for(HEIGHT, WIDTH)
    fast, _ = fe.fused_volumes(cpu_tsdf, HEIGHT, WIDTH, N, 2, weighted=False)
    pose = fe.moving_poses(2)[1]
    want = ref_raycast.raycast(to_reference_volume(fast), pose, camera, skip_empty=False)
    got = cpu_raycast.raycast(fast, pose, camera, skip_empty=not plain)
    np.testing.assert_array_equal(np.isnan(got.vertices), np.isnan(want.vertices))
    hit = ~np.isnan(want.vertices[..., 0])
    np.testing.assert_allclose(got.vertices[hit], want.vertices[hit], atol=1e-5, rtol=0)


@pytest.mark.parametrize("view", [(HEIGHT, WIDTH), (45, 77)], ids=["80x60", "77x45"])
def test_cpu_fine_skipping_is_bit_exact_with_back_faces(view):
    """Both levels of the cpu raycast's skipping (8^3 bricks, then fine bricks next to the
    surface), its per-pixel starts and its rays marched two at a time return the plain march's
    maps bit for bit, also from behind the fused wall, where rays meet negative samples first
    and stop at a back face; 77x45 leaves a partial band of rows and an odd pixel out."""
    camera = fe.camera_for(*view)
    fast, _ = fe.fused_volumes(cpu_tsdf, HEIGHT, WIDTH, 64, 2, weighted=False)
    behind = np.eye(4)
    behind[:3, :3] = np.diag([-1.0, 1.0, -1.0])  # looking back at the wall from z = 3.4 m
    behind[:3, 3] = [0.1, 0.05, 3.4]
    oblique = _oblique_pose_behind_wall()
    for name, pose in (("front", fe.moving_poses(2)[1]), ("behind", behind), ("oblique", oblique)):
        got = cpu_raycast.raycast(fast, pose, camera)
        want = cpu_raycast.raycast(fast, pose, camera, skip_empty=False)
        assert name != "front" or np.isfinite(want.vertices).mean() > 0.3
        np.testing.assert_array_equal(got.vertices, want.vertices)
        np.testing.assert_array_equal(got.normals, want.normals)
        np.testing.assert_array_equal(got.colours, want.colours)


def test_cpu_fine_skipping_stops_at_a_back_face():
    """A hand-made volume: unobserved up to a one-voxel sheet of negative TSDF at x = 20, then
    +1, and a second negative sheet at x = 40. Rays along +x whose sample lands on the first
    sheet see unknown, negative, positive: a back face, no surface (the sample after the sheet
    has no negative voxel near it, yet must be taken); the others pass it and hit the second
    sheet. The skipping march must tell the two apart exactly as the plain march does."""
    n = 64
    packed = np.zeros((n, n, n, 2), dtype=np.int16)
    packed[20:, :, :, 0] = 32767
    packed[20:, :, :, 1] = 1
    packed[20, :, :, 0] = packed[40, :, :, 0] = -16384
    volume = FastTsdfVolume(
        tsdf_weight=packed,
        colour=None,
        origin=np.zeros(3),
        voxel_size=0.05,
        truncation=2.05 * 0.05 / STEP_FRACTION,  # a step of 2.05 voxels
        max_weight=128.0,
    )
    pose = np.eye(4)
    pose[:3, :3] = [[0, 0, 1], [0, 1, 0], [-1, 0, 0]]  # the optical axis along world +x
    pose[:3, 3] = [-0.5, 1.6, 1.6]
    camera = fe.camera_for(HEIGHT, WIDTH)
    got = cpu_raycast.raycast(volume, pose, camera)
    want = cpu_raycast.raycast(volume, pose, camera, skip_empty=False)
    hit = np.isfinite(want.vertices[..., 0])
    assert 0.01 < hit.mean() < 0.99  # both outcomes occur
    np.testing.assert_array_equal(got.vertices, want.vertices)
    np.testing.assert_array_equal(got.normals, want.normals)


def test_cpu_capped_distance_is_the_capped_chessboard_distance():
    """The cpu raycast's capped distance maps (separable, vectorised) equal scipy's chessboard
    distance transform, capped, including sizes that are not a multiple of anything, caps
    past the size, and a map without any near brick."""
    from scipy import ndimage

    rng = np.random.default_rng(3)
    for m, density in ((5, 0.05), (33, 0.002), (40, 0.0)):
        near = rng.random((m, m, m)) < density
        for cap in (1, 3, 4, 8, 9, 16, 41, 60):  # 41, 60: shifts past the grid's size
            got = cpu_skip_maps._capped_distance(near, cap)
            if near.any():
                want = ndimage.distance_transform_cdt(~near, metric="chessboard")
                want = np.minimum(want, cap)
            else:
                want = np.full(near.shape, cap)
            np.testing.assert_array_equal(got, want)


def test_cpu_brick_distance_is_the_references_grown_chessboard_distance():
    """The brick map from negative bricks equals kintinuous_ref.raycast.empty_space's recipe
    (grow by one brick with scipy, then scipy's chessboard transform; 2 B when no brick is
    negative), for sparse, dense, single-brick and empty maps."""
    from scipy import ndimage

    rng = np.random.default_rng(5)
    single = np.zeros((9, 9, 9), dtype=bool)
    single[0, 8, 4] = True
    maps = [rng.random((b, b, b)) < density for b, density in ((4, 0.1), (32, 0.001), (17, 0.3))]
    for negative in (*maps, single, np.zeros((6, 6, 6), dtype=bool)):
        got = cpu_skip_maps._brick_distance(negative)
        grown = ndimage.binary_dilation(negative, structure=np.ones((3, 3, 3), dtype=bool))
        if grown.any():
            want = ndimage.distance_transform_cdt(~grown, metric="chessboard")
        else:
            want = np.full(negative.shape, 2 * len(negative))
        assert got.dtype == np.int64
        np.testing.assert_array_equal(got, want)


def test_cpu_negative_masks_kept_by_integration_equal_fresh_ones():
    """The per-fine-brick masks of observed negative voxels that integration keeps equal masks
    taken from scratch, before and after the moving volume shifts the buffer and clears slabs,
    and so does the `near` map built from them (against brute force: any such voxel among
    voxels 2f .. 2f + 2 per axis); the brick map is the reference's empty_space."""
    camera = fe.camera_for(HEIGHT, WIDTH)
    config = VolumeConfig(resolution=N, size=3.0, shift_threshold=2, min_extract_weight=1.0)
    poses = []
    for n in range(5):
        pose = np.eye(4)
        pose[:3, 3] = [0.1 * n, 0.02 * n, 0.05 * n]
        poses.append(pose)
    fast = cpu_tsdf.make_volume(config, poses[0])
    moving = MovingVolume(slab_view(fast), poses[0], config)
    colour = fe.scene_colour(HEIGHT, WIDTH)
    shifted_checked = False
    for index, pose in enumerate(poses):
        moving.update(pose)
        if fast.current_negative_masks() is None:  # stale after a shift: counted again here
            shifted_checked = index > 0
            cpu_raycast.raycast(fast, pose, camera)
        cpu_tsdf.integrate(fast, fe.scene_depth(HEIGHT, WIDTH, seed=index), pose, camera, colour)
        kept = fast.current_negative_masks()
        assert kept is not None and kept.any()
        recount = from_reference_volume(to_reference_volume(fast))
        recount.offset[:] = fast.offset
        np.testing.assert_array_equal(kept, cpu_skip_maps.negative_masks(recount))
        np.testing.assert_array_equal(
            cpu_skip_maps.skip_maps_and_near(fast)[2], _near_by_brute_force(fast)
        )
        np.testing.assert_array_equal(
            cpu_raycast.empty_space(fast), ref_raycast.empty_space(to_reference_volume(fast))
        )
    assert shifted_checked and fast.shifted


def _near_by_brute_force(volume: FastTsdfVolume) -> np.ndarray:
    """Per fine brick f: any observed negative voxel among the logical voxels 2f .. 2f + 2
    on every axis (those that a sample whose lower corner lies in f interpolates)."""
    tsdf_weight = np.roll(volume.tsdf_weight, [-o for o in volume.offsets()], axis=(0, 1, 2))
    negative = (tsdf_weight[..., 0] < 0) & (tsdf_weight[..., 1] > 0)
    m = -(-volume.resolution // FINE)
    near = np.zeros((m, m, m), dtype=bool)
    for f in np.ndindex(near.shape):
        window = tuple(slice(FINE * c, FINE * c + 3) for c in f)
        near[f] = negative[window].any()
    return near


def test_equivalence_cpu_moving_volume_shifts_slices_and_clears():
    """The camera slides 10 cm (1.07 voxels) per frame along x: the window shifts several times;
    the slices leaving and the final volume must match the reference's."""
    camera = fe.camera_for(HEIGHT, WIDTH)
    poses = []
    for n in range(6):
        pose = np.eye(4)
        pose[:3, 3] = [0.1 * n, 0.0, 0.0]
        poses.append(pose)
    reference = ref_tsdf.make_volume(CONFIG, poses[0])
    fast = cpu_tsdf.make_volume(CONFIG, poses[0])
    moving_ref = MovingVolume(reference, poses[0], CONFIG)
    moving_fast = MovingVolume(slab_view(fast), poses[0], CONFIG)
    colour = fe.scene_colour(HEIGHT, WIDTH)
    for index, pose in enumerate(poses):
        depth = fe.scene_depth(HEIGHT, WIDTH, seed=index)
        np.testing.assert_array_equal(moving_fast.update(pose), moving_ref.update(pose))
        ref_tsdf.integrate(reference, depth, pose, camera, colour)
        cpu_tsdf.integrate(fast, depth, pose, camera, colour)
    assert moving_ref.shifts >= 2 and reference.shifted  # the test really shifted
    np.testing.assert_allclose(fast.origin, reference.origin, atol=1e-12)
    assert_same_volume(fast, reference, len(poses))
    moving_ref.finish()
    moving_fast.finish()
    slices_ref, slices_fast = list(moving_ref.store), list(moving_fast.store)
    assert len(slices_ref) == len(slices_fast) >= 2
    for got, want in zip(slices_fast, slices_ref, strict=True):
        # marching cubes over TSDFs within 0.5 n / 32767 of each other: same triangles, vertices
        # within a hair (an edge crossing moves by voxel * dF / |F1 - F0|)
        assert len(got.triangles) == len(want.triangles)
        np.testing.assert_allclose(got.points, want.points, atol=1e-3)


def test_slab_view_reads_and_clears_only_the_box():
    reference, _ = fe.fused_volumes(cpu_tsdf, HEIGHT, WIDTH, N, 1, weighted=False)
    reference = to_reference_volume(reference)
    reference.offset[:] = OFFSET
    fast = from_reference_volume(reference)
    view = slab_view(fast)
    cells = reference.cells((0, 0, 3), (N, N, 9))  # wraps along x and z
    np.testing.assert_array_equal(view.tsdf[cells], reference.tsdf[cells])
    np.testing.assert_array_equal(view.colour[cells], reference.colour[cells])
    view.weight[cells] = 0.0
    back = to_reference_volume(fast)
    cleared = np.zeros(reference.weight.shape, dtype=bool)
    cleared[cells] = True
    assert reference.weight[cleared].any() and not back.weight[cleared].any()
    np.testing.assert_array_equal(back.weight[~cleared], reference.weight[~cleared])
    view.colour[cells] = 0.0
    back = to_reference_volume(fast)
    assert reference.colour_weight[cleared].any() and not back.colour_weight[cleared].any()
    np.testing.assert_array_equal(back.colour_weight[~cleared], reference.colour_weight[~cleared])


def test_cpu_near_starts_skip_only_samples_that_cannot_be_negative():
    """The cpu raycast starts each ray where it first enters a fine brick that may hold a
    negative sample (raycast.cpu_near_starts.near_starts: slab tests against the boxes of the
    `near` fine bricks). Checked against every sample of every ray (the reference-equivalent
    sample_tsdf): none before its pixel's start is negative; looking at the fused wall the
    starts skip most samples before the first negative one; from behind the volume, where rays
    meet the wall's back at once, and from inside it, they still hold. And for 300 pixels each
    start lies between two first entries found by brute force (float64 slab tests against every
    near box): into the boxes themselves, and into the boxes grown by twice the float32 test's
    margin, less twice its slack."""
    camera = fe.camera_for(HEIGHT, WIDTH)
    fast, _ = fe.fused_volumes(cpu_tsdf, HEIGHT, WIDTH, 64, 2, weighted=False)
    near = cpu_skip_maps.skip_maps_and_near(fast)[2]
    inside = np.eye(4)
    inside[:3, 3] = np.asarray(fast.origin) + 0.5 * fast.resolution * fast.voxel_size
    slanted = np.eye(4)  # optical axis nearer x than z: near_starts takes boxes one by one
    angle = np.radians(50.0)
    slanted[:3, :3] = [
        [np.cos(angle), 0, np.sin(angle)],
        [0, 1, 0],
        [-np.sin(angle), 0, np.cos(angle)],
    ]
    slanted[:3, 3] = [-1.0, 0.0, 0.0]
    views = (
        ("front", fe.moving_poses(2)[1]), ("behind", _oblique_pose_behind_wall()),
        ("inside", inside), ("slanted", slanted),
    )  # fmt: skip
    pixels = np.random.default_rng(5).integers(0, (WIDTH, HEIGHT), (300, 2))
    for name, pose in views:
        start = cpu_near_starts.near_starts(fast, near, pose, camera)
        exact = _first_near_entry(fast, near, pose, camera, pixels)
        margin = 2 * cpu_near_starts.ENTRY_MARGIN
        grown = _first_near_entry(fast, near, pose, camera, pixels, margin)
        got = start[pixels[:, 1], pixels[:, 0]]
        assert np.isfinite(exact).sum() > 30, name
        assert np.all(got <= exact), name
        assert np.all(got >= grown * (1 - 2 * cpu_near_starts.ENTRY_SLACK)), name
        t, values = _samples_of_every_ray(fast, pose, camera)
        assert not np.any(values[t < start[..., None]] < 0), name
        negative = values < 0
        before_negative = np.where(negative.any(axis=2), negative.argmax(axis=2), t.shape[2])
        skipped = np.count_nonzero(t < start[..., None], axis=2)
        if name == "front":
            assert np.median(before_negative) > 10
            assert np.median(skipped) > 0.7 * np.median(before_negative)


def _first_near_entry(volume, near, pose, camera, pixels, grow: float = 0.0) -> np.ndarray:
    """Per pixel (u, v), the ray distance where its ray first enters the closed box of a
    `near` fine brick grown by `grow` metres on every side (inf: it enters none), by float64
    slab tests against all of them."""
    intrinsics = np.array([camera.fx, camera.fy, camera.cx, camera.cy])
    rotation, origin = np.ascontiguousarray(pose[:3, :3]), pose[:3, 3]
    size = FINE * volume.voxel_size
    lower = np.asarray(volume.origin) + size * np.argwhere(near) - origin - grow
    size += 2 * grow
    entries = []
    for u, v in pixels:
        direction = np.array(cpu_ops.OPS.ray_direction(u, v, intrinsics, rotation))
        direction[direction == 0] = 1e-300  # parallel to a face: its slab is all or nothing
        with np.errstate(over="ignore"):
            near_face, far_face = lower / direction, (lower + size) / direction
        enter = np.maximum(np.minimum(near_face, far_face).max(axis=1), 0.0)
        leave = np.maximum(near_face, far_face).min(axis=1)
        entries.append(enter[enter <= leave].min(initial=np.inf))
    return np.array(entries)


def _samples_of_every_ray(volume, pose, camera) -> tuple[np.ndarray, np.ndarray]:
    """(t, F), (H, W, S) each: the plain march's sample parameters of every pixel's ray and the
    TSDF there (F NaN, t inf past the ray's exit)."""
    intrinsics = np.array([camera.fx, camera.fy, camera.cx, camera.cy])
    rotation, origin = np.ascontiguousarray(pose[:3, :3]), np.ascontiguousarray(pose[:3, 3])
    volume_origin = np.asarray(volume.origin, dtype=np.float64)
    directions = np.array(
        [[cpu_ops.OPS.ray_direction(u, v, intrinsics, rotation) for u in range(camera.width)]
         for v in range(camera.height)]
    )  # fmt: skip
    span = np.array(
        [[cpu_ops.OPS.ray_span(origin, tuple(d), volume_origin, volume.voxel_size,
                                    volume.resolution) for d in row] for row in directions]
    )  # fmt: skip
    step = STEP_FRACTION * volume.truncation
    count = int(np.ceil(volume.resolution * np.sqrt(3) * volume.voxel_size / step)) + 1
    t = span[..., :1] + step * np.arange(count)
    t[t > span[..., 1:]] = np.inf
    points = origin + np.nan_to_num(t, posinf=-1e3)[..., None] * directions[..., None, :]
    values = cpu_tsdf.sample_tsdf(
        volume, ((points - volume_origin) / volume.voxel_size).reshape(-1, 3)
    )
    return t, np.where(np.isfinite(t), values.reshape(t.shape), np.nan)


def _oblique_pose_behind_wall() -> np.ndarray:
    """Looking back at the fused wall from z = 3.2 m, rotated 35 degrees about y."""
    pose = np.eye(4)
    angle = np.radians(35.0)
    pose[:3, :3] = [
        [-np.cos(angle), 0, -np.sin(angle)],
        [0, 1, 0],
        [np.sin(angle), 0, -np.cos(angle)],
    ]
    pose[:3, 3] = [1.2, 0.0, 3.2]
    return pose
