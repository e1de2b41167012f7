# ruff: noqa: ANN001, ANN201  (numba kernels and loops: argument types come from the call)
"""kintinuous_ref.tsdf as CUDA kernels: integration with one thread per voxel column (threads
over (k, j), x marched inside the thread, as KinectFusion's GPU design) around
kintinuous_fast.tsdf.ops, into a FastTsdfVolume in device memory (8 bytes per voxel).

Per frame only the pose, four intrinsics and the frustum box cross from the host; depth, colour
and colour weights may be device arrays (a host array is uploaded for the call).
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numba import cuda

from kintinuous_fast.targets import cuda_device_jit, pinhole, to_host
from kintinuous_fast.targets.cuda import BLOCK_1D, BLOCK_2D, grid_1d, grid_2d, like_input, to_device
from kintinuous_fast.tsdf import ops as integration
from kintinuous_fast.tsdf import voxel
from kintinuous_fast.tsdf.volume import (
    FastTsdfVolume,
    camera_frame_steps,
    check_volume_memory,
    colour_inputs,
    frustum_box,
    fusion_limits,
    image_size,
    index_box,
    memory_bytes,
    projection_constants,
    to_reference_volume,
    volume_header,
)
from kintinuous_ref.camera import Intrinsics
from kintinuous_ref.config import VolumeConfig
from kintinuous_ref.tsdf import (
    VoxelGrid,
    check_depth,
    corner_weights,
    refuse_if_too_big,
    trilinear,
    volume_origin,
)
from kintinuous_ref.tsdf import available_memory_bytes as _host_memory_bytes

__all__ = [
    "FastTsdfVolume",
    "VoxelGrid",
    "available_memory_bytes",
    "check_depth",
    "check_volume_config",
    "corner_weights",
    "integrate",
    "make_volume",
    "memory_bytes",
    "refuse_if_too_big",
    "sample_tsdf",
    "to_reference_volume",
    "trilinear",
    "volume_origin",
]

_voxels = voxel.build_ops(cuda_device_jit())
_ops = integration.build_ops(cuda_device_jit(), _voxels)
integrate_voxel = _ops.integrate_voxel
ray_distance_pixel = _ops.ray_distance_pixel
sample_tsdf_at = _voxels.sample_tsdf_at


@cuda.jit
def _fill_kernel(flat, value):
    # Grid-stride loop: each thread writes every (total threads)-th element.
    start, stride = cuda.grid(1), cuda.gridsize(1)
    for index in range(start, flat.shape[0], stride):
        flat[index] = value


@cuda.jit
def _max_depth_kernel(depth, result):
    # Largest valid depth: one atomic per thread with depth (a reduction small enough here).
    u, v = cuda.grid(2)
    if v < depth.shape[0] and u < depth.shape[1] and depth[v, u] > 0:
        cuda.atomic.max(result, 0, depth[v, u])


@cuda.jit
def _ray_distance_kernel(depth, camera, out):
    # flat, with -inf in the "no pixel" slot one past the image (tsdf.ops.project_voxel)
    u, v = cuda.grid(2)
    height, width = depth.shape
    if v < height and u < width:
        out[v * width + u] = ray_distance_pixel(depth[v, u], u, v, camera)
    if u == 0 and v == 0:
        out[height * width] = -np.inf


@cuda.jit
def _integrate_kernel(
    tsdf_weight,
    colour_volume,
    offsets,
    box,
    base,
    steps,
    intrinsics,
    image_size,
    ray_distance,
    limits,
    colour,
    colour_weights,
    fuse_colour,
):
    # `box` = (lo, hi): voxel indices [lo, hi); `limits` = tsdf.ops.fuse_voxel's
    lo, hi = box
    dk, dj = cuda.grid(2)
    k, j = lo[2] + dk, lo[1] + dj
    if k < hi[2] and j < hi[1]:
        for i in range(lo[0], hi[0]):
            integrate_voxel(
                tsdf_weight,
                colour_volume,
                (i, j, k),
                offsets,
                base,
                steps,
                intrinsics,
                image_size,
                ray_distance,
                limits,
                colour,
                colour_weights,
                fuse_colour,
            )


@cuda.jit
def _sample_kernel(tsdf_weight, o0, o1, o2, coordinates, out):
    m = cuda.grid(1)
    if m < out.shape[0]:
        out[m] = sample_tsdf_at(
            tsdf_weight, o0, o1, o2, coordinates[m, 0], coordinates[m, 1], coordinates[m, 2]
        )


def _zeros(shape: tuple[int, ...], dtype: Any) -> Any:
    """A device array of zeros made on the device (no host buffer of the volume's size)."""
    array = cuda.device_array(shape, dtype=dtype)
    flat = array.reshape(-1)
    blocks = min(grid_1d(flat.shape[0] // 64 + 1), 4096)  # >= 64 elements per thread
    _fill_kernel[blocks, BLOCK_1D](flat, 0)
    return array


def available_memory_bytes() -> int:
    """The GPU's free memory, where the cuda volume lives; host memory is not what limits it.
    Under numba's simulator, which has no memory info and keeps device arrays in host memory,
    the host's available memory."""
    try:
        return int(cuda.current_context().get_memory_info()[0])
    except Exception:  # the simulator's context has no memory info
        return _host_memory_bytes()


def check_volume_config(config: VolumeConfig) -> None:
    """Refuse, in one line, a volume (8 bytes per voxel, memory_bytes) that does not fit in the
    GPU's free memory (available_memory_bytes)."""
    check_volume_memory(config, available_memory_bytes())


def make_volume(
    config: VolumeConfig, first_pose: np.ndarray, colour_max_weight: float = 255.0
) -> FastTsdfVolume:
    """An empty volume in device memory placed for the first camera pose (all weights 0)."""
    check_volume_config(config)
    n = config.resolution
    return FastTsdfVolume(
        tsdf_weight=_zeros((n, n, n, 2), np.int16),
        colour=_zeros((n, n, n, 4), np.uint8) if config.colour else None,
        **volume_header(config, first_pose, colour_max_weight),
    )


def integrate(
    volume: FastTsdfVolume,
    depth: Any,
    pose: np.ndarray,
    camera: Intrinsics,
    colour: Any = None,
    colour_weights: Any = None,
) -> None:
    """Fuse one depth map (and optionally its colour) into the device volume, in place; the
    update rule is kintinuous_ref.tsdf.integrate's, rounded to the stored types."""
    check_depth(depth, camera)
    d_depth = to_device(depth, np.float32)
    grid = grid_2d(camera.height, camera.width)
    largest = cuda.to_device(np.zeros(1, dtype=np.float32))
    _max_depth_kernel[grid, BLOCK_2D](d_depth, largest)
    box = frustum_box(volume, float(to_host(largest)[0]), pose, camera)
    if box is None:
        return
    ray_distance = cuda.device_array(camera.height * camera.width + 1, dtype=np.float32)
    _ray_distance_kernel[grid, BLOCK_2D](d_depth, pinhole(camera), ray_distance)
    fuse_colour, colour, colour_weights, colour_volume = colour_inputs(
        volume, depth, colour, colour_weights, to_device
    )
    base, steps = camera_frame_steps(volume, pose)
    lo, hi = index_box(box)
    threads = grid_2d(hi[1] - lo[1], hi[2] - lo[2])  # x: k (contiguous in memory), y: j
    _integrate_kernel[threads, BLOCK_2D](
        volume.tsdf_weight,
        colour_volume,
        volume.offsets(),
        (lo, hi),
        cuda.to_device(base),
        cuda.to_device(steps),
        cuda.to_device(projection_constants(camera)),
        image_size(camera),
        ray_distance,
        fusion_limits(volume),
        colour,
        colour_weights,
        fuse_colour,
    )


def sample_tsdf(volume: FastTsdfVolume, coordinates: Any) -> Any:
    """Trilinear TSDF over observed voxels at continuous voxel coordinates (M, 3); NaN where
    none of the 8 is observed or outside the grid (kintinuous_ref.tsdf.sample_tsdf)."""
    d_coordinates = to_device(coordinates, np.float64)
    out = cuda.device_array(d_coordinates.shape[0], dtype=np.float64)
    _sample_kernel[grid_1d(out.shape[0]), BLOCK_1D](
        volume.tsdf_weight, *volume.offsets(), d_coordinates, out
    )
    return like_input(out, coordinates)
