"""kintinuous_fast.mesh's marching cubes equals the reference's (kintinuous_ref.marching_cubes):
the same vertices in the same order, bit for bit, and the same triangles, on a sphere, a random
field and a field with unobserved regions; cpu in this process, cuda on the GPU or in numba's
CUDA simulator (a child process), where every thread is a Python thread: there the volumes are
10^3."""

from pathlib import Path

import numpy as np
import pytest

from kintinuous_fast import cuda_status
from kintinuous_ref import marching_cubes as reference

on_device = pytest.mark.skipif(
    bool(cuda_status()), reason="no CUDA GPU: runs in the simulator subprocess below"
)


def sphere(n):
    centre = (n - 1) / 2 + np.array([0.31, -0.17, 0.07])
    grid = np.indices((n, n, n)).transpose(1, 2, 3, 0) - centre
    field = (np.linalg.norm(grid, axis=-1) - 0.35 * n).astype(np.float32)
    return field, np.ones_like(field), 0.0


def random_field(n):
    rng = np.random.default_rng(n)
    field = rng.standard_normal((n, n + 1, n - 1)).astype(np.float32)
    field[2, 3, 1] = 0.0  # a vertex on a voxel
    return field, np.ones_like(field), 0.0


def partly_observed(n):
    rng = np.random.default_rng(n + 1)
    field = rng.standard_normal((n, n, n)).astype(np.float32)
    weight = np.where(rng.random(field.shape) < 0.8, 5.0, 1.0).astype(np.float32)
    weight[: n // 3] = 0.0
    return field, weight, 1.0


CASES = [sphere, random_field, partly_observed]


def check_equal(marching_cubes, case, n):
    tsdf, weight, min_weight = case(n)
    expected = reference.marching_cubes(tsdf, weight, min_weight)
    vertices, triangles = marching_cubes(tsdf, weight, min_weight)
    assert len(expected[1]) > 0
    np.testing.assert_array_equal(vertices, expected[0])
    np.testing.assert_array_equal(triangles, expected[1])
    assert vertices.dtype == np.float64 and triangles.dtype == np.int64


@pytest.mark.parametrize("case", CASES, ids=lambda case: case.__name__)
def test_cpu_marching_cubes_equals_the_reference(case):
    from kintinuous_fast.mesh import cpu

    check_equal(cpu.marching_cubes, case, 20)


def half_spaces(n):
    """Rows of voxels without a crossing whose neighbours have the other sign (the x plane:
    rows of cubes that hold surface from end to end), beside a z plane (every row crossed
    at the same place) and a row crossed at its two ends only."""
    i, _, k = np.indices((n, n - 2, n + 3))
    field = np.where(k < n // 2, i - n / 3 - 0.25, k - n / 2 - 0.4).astype(np.float32)
    field[n - 3, 2] = 1.0
    field[n - 3, 2, [0, -1]] = -1.0
    return field, np.ones_like(field), 0.0


def signed_zeros(n):
    """Zeros of both signs (both count as outside) among +-1, with unobserved voxels."""
    rng = np.random.default_rng(n + 2)
    field = rng.choice(np.array([-1.0, -0.0, 0.0, 1.0], np.float32), (n, n - 1, n + 1))
    weight = np.where(rng.random(field.shape) < 0.9, 2.0, 0.0).astype(np.float32)
    return field, weight, 0.0


@pytest.mark.parametrize("case", [half_spaces, signed_zeros], ids=lambda case: case.__name__)
def test_cpu_marching_cubes_trims_equal_the_reference(case):
    """Rows trimmed to the crossings of their four rows of voxels, and widened to their ends
    where those differ in sign there, lose no cube."""
    from kintinuous_fast.mesh import cpu

    check_equal(cpu.marching_cubes, case, 17)


@pytest.mark.parametrize("shape", [(2, 2, 2), (5, 2, 2), (2, 3, 7), (4, 6, 2), (3, 9, 40)])
def test_cpu_marching_cubes_of_thin_volumes(shape):
    from kintinuous_fast.mesh import cpu

    rng = np.random.default_rng(sum(shape))
    for _ in range(20):
        field = rng.standard_normal(shape).astype(np.float32)
        weight = rng.random(shape).astype(np.float32)
        expected = reference.marching_cubes(field, weight, 0.1)
        vertices, triangles = cpu.marching_cubes(field, weight, 0.1)
        np.testing.assert_array_equal(vertices, expected[0])
        np.testing.assert_array_equal(triangles, expected[1])


def test_cpu_marching_cubes_of_nothing():
    from kintinuous_fast.mesh import cpu

    field = np.ones((5, 5, 5), np.float32)
    assert cpu.marching_cubes(field, field, 0.0)[1].shape == (0, 3)
    assert cpu.marching_cubes(field[:1], field[:1], 0.0)[0].shape == (0, 3)


@pytest.mark.skipif(not cuda_status(), reason="CUDA works here: the tests run in this process")
@pytest.mark.cuda_simulator(Path(__file__), "-k", "not in_simulator")
def test_cuda_marching_cubes_in_simulator(cuda_simulator):
    cuda_simulator()


@on_device
@pytest.mark.parametrize("case", CASES, ids=lambda case: case.__name__)
def test_cuda_marching_cubes_equals_the_reference(case):
    from kintinuous_fast.backend import cuda_is_simulated
    from kintinuous_fast.mesh import cuda

    check_equal(cuda.marching_cubes, case, 10 if cuda_is_simulated() else 40)
