"""The mesh stages' mesh_box (the moving volume's slices: the surface of a box of a cyclical
volume by kintinuous_ref.box_surface's rules) on the fast backends equals the reference's rules
on the same fast volume, bit for bit: vertices, triangles, colours and grid edges, for boxes
that wrap around the buffer. The cuda one meshes the box on the device and downloads only the
surface (counted in targets.TRAFFIC); cpu here, cuda on a GPU or in numba's CUDA simulator (a
child process, every thread a Python thread: volumes of 12^3)."""

from pathlib import Path

import numpy as np
import pytest

from kintinuous_fast import cuda_status
from kintinuous_fast.tsdf.volume import (
    FastTsdfVolume,
    from_reference_volume,
    slab_view,
    to_reference_volume,
)
from kintinuous_ref import box_surface, slices
from kintinuous_ref import marching_cubes as reference
from kintinuous_ref.config import VolumeConfig
from kintinuous_ref.moving_volume import MovingVolume
from kintinuous_ref.tsdf import TsdfVolume

on_device = pytest.mark.skipif(
    bool(cuda_status()), reason="no CUDA GPU: runs in the simulator subprocess below"
)
N = 12
MIN_WEIGHT = 4.0
WRAPS = (10, 0, 7)  # the buffer's offset: a box at the start of x and z wraps around
SLAB = ((0, 0, 0), (5, N, N))  # five layers along x (cells 10, 11, 0, 1, 2)


def sphere_volume(offset: tuple[int, int, int], colour: bool = True, seed: int = 1):
    """A fast volume of N^3 voxels holding a sphere's TSDF at the buffer offset `offset`, with
    weights from 0 to 11 (so min_weight 4 leaves a patchwork of observed voxels) and colours
    that some voxels never received."""
    rng = np.random.default_rng(seed)
    centre = (N - 1) / 2 + np.array([0.31, -0.17, 0.07])
    grid = np.indices((N, N, N)).transpose(1, 2, 3, 0) - centre
    tsdf = np.clip((np.linalg.norm(grid, axis=-1) - 0.3 * N) / 3, -1, 1).astype(np.float32)
    # Vertices on a voxel and within ON_EDGE of one: the two voxels of the slab (logical x < 5)
    # nearest the surface at exactly 0 and at the smallest positive int16 TSDF.
    nearest = np.unravel_index(np.argsort(np.abs(tsdf[:5]), axis=None)[:2], (5, N, N))
    tsdf[nearest] = (0.0, 1.0 / 32767.0)
    weight = rng.integers(0, 12, (N, N, N)).astype(np.float32)
    for i, j, k in zip(*nearest, strict=True):  # observed around them, so the slices keep them
        weight[max(i - 1, 0) : i + 2, max(j - 1, 0) : j + 2, max(k - 1, 0) : k + 2] = 11.0
    rgb = rng.integers(0, 256, (N, N, N, 3)).astype(np.float32)
    colour_weight = np.where(rng.random((N, N, N)) < 0.7, 5.0, 0.0).astype(np.float32)

    def stored(logical: np.ndarray) -> np.ndarray:  # logical voxel l in cell (l + offset) mod N
        return np.roll(logical, tuple(offset), axis=(0, 1, 2))

    volume = TsdfVolume(
        tsdf=stored(tsdf),
        weight=stored(weight),
        colour=stored(rgb) if colour else None,
        colour_weight=stored(colour_weight) if colour else None,
        origin=np.zeros(3),
        voxel_size=0.01,
        truncation=0.03,
        max_weight=100.0,
        offset=np.array(offset, dtype=np.int64),
    )
    return from_reference_volume(volume)


def reference_surface(fast: FastTsdfVolume, lo, hi) -> box_surface.BoxSurface:
    """The reference's rules on the fast volume's (dequantised) values."""
    return reference.mesh_box(to_reference_volume(fast), lo, hi, MIN_WEIGHT)


def assert_same_surface(found: box_surface.BoxSurface, expected: box_surface.BoxSurface) -> None:
    assert len(expected.triangles) > 0
    for name in ("vertices", "triangles", "colours", "edges"):
        value, truth = getattr(found, name), getattr(expected, name)
        assert value.dtype == truth.dtype, name
        np.testing.assert_array_equal(value, truth, err_msg=name)


def test_the_keys_code_of_a_vertex_on_a_voxel_is_the_slices():
    assert box_surface.ON_VOXEL == slices.ON_VOXEL


def test_a_wrapped_box_is_the_same_surface_as_unwrapped():
    """The offset moves the cells, not the surface: the slab of a volume stored at WRAPS has the
    vertices, triangles, colours and edges of the same slab stored at offset 0."""
    wrapped = reference_surface(sphere_volume(WRAPS), *SLAB)
    plain = reference_surface(sphere_volume((0, 0, 0)), *SLAB)
    assert_same_surface(wrapped, plain)


def test_a_kept_vertex_has_both_voxels_of_its_edge_observed():
    """Both voxels of each kept vertex's edge reach min_weight, the rule leaves out part of the
    surface of the test volume (so it is exercised), and the slab keeps vertices on voxels."""
    volume = to_reference_volume(sphere_volume(WRAPS))
    surface = reference.mesh_box(volume, *SLAB, MIN_WEIGHT)
    weight = volume.weight[volume.cells(*SLAB)]
    lower = surface.edges[:, :3]
    upper = lower + np.eye(4, 3, dtype=np.int64)[surface.edges[:, 3]]
    assert (weight[tuple(lower.T)] >= MIN_WEIGHT).all()
    assert (weight[tuple(upper.T)] >= MIN_WEIGHT).all()
    everything = reference.mesh_box(volume, *SLAB, 0.0)
    assert len(everything.triangles) > 2 * len(surface.triangles) > 0
    assert (surface.edges[:, 3] == box_surface.ON_VOXEL).sum() >= 2


@pytest.mark.parametrize("colour", [True, False], ids=["colour", "no_colour"])
def test_cpu_mesh_box_equals_the_reference(colour):
    from kintinuous_fast.mesh import cpu

    fast = sphere_volume(WRAPS, colour)
    assert_same_surface(cpu.mesh_box(fast, *SLAB, MIN_WEIGHT), reference_surface(fast, *SLAB))
    whole = ((0, 0, 0), (N, N, N))
    found = cpu.mesh_box(slab_view(fast), *whole, MIN_WEIGHT)
    assert_same_surface(found, reference_surface(fast, *whole))


def moving_volume_slices(volume, mesh_box) -> list:
    """The slices of a shift by 4 voxels along x, then of the rest of the window, with the
    moving volume extracting them through `mesh_box`."""
    config = VolumeConfig(resolution=N, size=0.12, shift_threshold=2, min_extract_weight=4.0)
    moving = MovingVolume(volume, np.eye(4), config, mesh_box=mesh_box)
    moving.fused = 8
    moving.shift_axis(0, 4)
    moving.finish()
    return list(moving.store)


def assert_same_slices(found: list, expected: list) -> None:
    assert len(found) == len(expected) == 2
    for mesh, truth in zip(found, expected, strict=True):
        for name in ("points", "keys", "triangles", "colours", "box_lo", "box_hi"):
            np.testing.assert_array_equal(getattr(mesh, name), getattr(truth, name), name)


def test_moving_volume_slices_use_the_backends_mesh_box():
    """A shift and the last slice through MovingVolume with the cpu mesh stage's mesh_box on a
    fast volume give the slices of the reference's on the same values (world points and keys
    from the same surface)."""
    from kintinuous_fast.mesh import cpu

    expected = moving_volume_slices(to_reference_volume(sphere_volume(WRAPS)), reference.mesh_box)
    found = moving_volume_slices(slab_view(sphere_volume(WRAPS)), cpu.mesh_box)
    assert_same_slices(found, expected)


@pytest.mark.skipif(not cuda_status(), reason="CUDA works here: the tests run in this process")
@pytest.mark.cuda_simulator(Path(__file__), "-k", "cuda and not in_simulator")
def test_cuda_mesh_box_in_simulator(cuda_simulator):
    cuda_simulator()


def device_volume(fast: FastTsdfVolume) -> FastTsdfVolume:
    """The same volume in device memory, as the cuda backend keeps it."""
    from kintinuous_fast.targets.cuda import to_device

    fast.tsdf_weight = to_device(fast.tsdf_weight)
    fast.colour = None if fast.colour is None else to_device(fast.colour)
    return fast


@on_device
def test_cuda_mesh_box_of_a_wrapped_slab_downloads_only_the_surface():
    """The slab that wraps around the buffer, with colours: the reference's surface, and the
    bytes it downloads are the two totals' 32, 27 a vertex and 24 a triangle: nothing of the
    size of the box."""
    from kintinuous_fast.mesh import cuda
    from kintinuous_fast.targets import TRAFFIC

    expected = reference_surface(sphere_volume(WRAPS), *SLAB)
    fast = device_volume(sphere_volume(WRAPS))
    before = TRAFFIC.bytes_to_host
    found = cuda.mesh_box(slab_view(fast), *SLAB, MIN_WEIGHT)
    downloaded = TRAFFIC.bytes_to_host - before
    assert_same_surface(found, expected)
    vertices, triangles = len(found.vertices), len(found.triangles)
    assert downloaded == 32 + 27 * vertices + 24 * triangles
    # Even this tiny box, whose surface crosses a third of its cubes, downloads less than its
    # TSDF and weights would (4 bytes a voxel); a real slab's surface is a far smaller share.
    assert downloaded < 4 * 5 * N * N


@on_device
def test_cuda_mesh_box_of_the_whole_volume_without_colour():
    """The whole window (the last slice, and a recentre's), offset on all three axes, without a
    colour volume: black vertices, nothing but vertices and triangles downloaded."""
    from kintinuous_fast.mesh import cuda
    from kintinuous_fast.targets import TRAFFIC

    offset, whole = (3, 11, 6), ((0, 0, 0), (N, N, N))
    expected = reference_surface(sphere_volume(offset, colour=False), *whole)
    fast = device_volume(sphere_volume(offset, colour=False))
    before = TRAFFIC.bytes_to_host
    found = cuda.mesh_box(fast, *whole, MIN_WEIGHT)
    assert_same_surface(found, expected)
    assert not found.colours.any()
    downloaded = TRAFFIC.bytes_to_host - before
    assert downloaded == 32 + 24 * len(found.vertices) + 24 * len(found.triangles)


@on_device
def test_cuda_moving_volume_slices_equal_the_references():
    """The moving volume on a device volume (its SlabView, as the pipeline gives it) with the
    cuda mesh_box: the reference's slices, and the shift clears the leaving cells on the
    device (no download beyond the two slices' surfaces)."""
    from kintinuous_fast.mesh import cuda
    from kintinuous_fast.targets import TRAFFIC

    expected = moving_volume_slices(to_reference_volume(sphere_volume(WRAPS)), reference.mesh_box)
    before = TRAFFIC.bytes_to_host
    found = moving_volume_slices(slab_view(device_volume(sphere_volume(WRAPS))), cuda.mesh_box)
    assert_same_slices(found, expected)
    surfaces = sum(32 + 27 * len(mesh.points) + 24 * len(mesh.triangles) for mesh in found)
    assert TRAFFIC.bytes_to_host - before == surfaces
