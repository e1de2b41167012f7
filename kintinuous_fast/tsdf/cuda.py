# ruff: noqa: ANN001, ANN201  (numba kernels and loops: argument types come from the call)
"""kintinuous_ref.tsdf as CUDA kernels: integration with one thread per voxel column (threads
over (k, j), x marched inside the thread, as KinectFusion's GPU design) around
kintinuous_fast.tsdf.ops, into a FastTsdfVolume in device memory (8 bytes per voxel).

Per frame only launch parameters cross from the host (the pose's camera-frame steps, four
intrinsics, the frustum box), and nothing comes back: depth, colour and colour weights may be
device arrays (a host array is uploaded for the call), and the frame's largest depth, which
bounds the voxels a frame can update, stays on the device where the kernel reads it. (A copy
between host and device waits for the device to finish the work queued before it, so either way
the host would stall once per frame.)
"""

from __future__ import annotations

import functools
from typing import Any

import numpy as np
from numba import cuda

from kintinuous_fast.targets import cuda_device_jit, pinhole
from kintinuous_fast.targets.cuda import (
    BLOCK_1D,
    BLOCK_2D,
    copy_up,
    grid_1d,
    grid_2d,
    kernel,
    like_input,
    pooled_array,
    to_device,
)
from kintinuous_fast.targets.cuda_graphs import segment, signed
from kintinuous_fast.tsdf import ops as integration
from kintinuous_fast.tsdf import voxel
from kintinuous_fast.tsdf.volume import (
    FastTsdfVolume,
    camera_frame_steps,
    check_volume_memory,
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
column_range = _ops.column_range
ray_distance_pixel = _ops.ray_distance_pixel
sample_tsdf_at = _voxels.sample_tsdf_at


@kernel
def _fill_kernel(flat, value):
    # Grid-stride loop: each thread writes every (total threads)-th element.
    start, stride = cuda.grid(1), cuda.gridsize(1)
    for index in range(start, flat.shape[0], stride):
        flat[index] = value


@kernel
def _max_depth_kernel(depth, result):
    # Largest valid depth: one atomic per thread with depth (a reduction small enough here).
    u, v = cuda.grid(2)
    if v < depth.shape[0] and u < depth.shape[1] and depth[v, u] > 0:
        cuda.atomic.max(result, 0, depth[v, u])


@kernel
def _depth_weights_kernel(depth, out):
    # flat colour weights: 1 where there is depth, else 0 (the reference's default)
    u, v = cuda.grid(2)
    height, width = depth.shape
    if v < height and u < width:
        out[v * width + u] = np.float32(1.0) if depth[v, u] > 0 else np.float32(0.0)


@kernel
def _ray_distance_kernel(depth, camera, out):
    # flat, with -inf in the "no pixel" slot one past the image (tsdf.ops.project_voxel)
    u, v = cuda.grid(2)
    height, width = depth.shape
    if v < height and u < width:
        out[v * width + u] = ray_distance_pixel(depth[v, u], u, v, camera)
    if u == 0 and v == 0:
        out[height * width] = -np.inf


@cuda.jit(device=True)
def _column_span(base, steps, j, k, intrinsics, image_size, far, n):
    """[i0, i1): the voxels (i, j, k) of the column along x that can project into the image no
    farther than z = `far` (tsdf.ops.column_range, from the column's camera-frame start in
    float64; its voxel of margin covers the float32 positions integrate_voxel computes)."""
    fj, fk = float(j), float(k)
    start = (
        float(base[0]) + fj * float(steps[1, 0]) + fk * float(steps[2, 0]),
        float(base[1]) + fj * float(steps[1, 1]) + fk * float(steps[2, 1]),
        float(base[2]) + fj * float(steps[1, 2]) + fk * float(steps[2, 2]),
    )
    step = (float(steps[0, 0]), float(steps[0, 1]), float(steps[0, 2]))
    return column_range(start, step, intrinsics, image_size, far, n)


@kernel
def _integrate_kernel(
    tsdf_weight,
    colour_volume,
    placement,
    frame,
    largest,
    bounded,
    intrinsics,
    image_size,
    ray_distance,
    limits,
    colour,
    colour_weights,
    fuse_colour,
):
    # `frame` (6, 3) float32 (frame_constants): rows 0-2 the voxel steps, row 3 the base, rows
    # 4-5 the box [lo, hi) of voxel indices; one thread per column (j, k) of the volume, those
    # outside the box return. If `bounded`, each column only where z <= the frame's largest
    # depth (1,) `largest` + mu, as frustum_box; `limits` = fuse_voxel's; the buffer offset
    # is row 0 of `placement` (volume_placement)
    steps, base = frame, frame[3]
    offsets = (int(placement[0, 0]), int(placement[0, 1]), int(placement[0, 2]))
    k, j = cuda.grid(2)
    inside_k = int(frame[4, 2]) <= k and k < int(frame[5, 2])
    if inside_k and int(frame[4, 1]) <= j and j < int(frame[5, 1]):
        first, end = int(frame[4, 0]), int(frame[5, 0])
        if bounded:
            far = float(largest[0]) + float(limits[0])
            n = tsdf_weight.shape[0]
            span = _column_span(base, steps, j, k, intrinsics, image_size, far, n)
            first, end = max(first, span[0]), min(end, span[1])
        for i in range(first, end):
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


@kernel
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


@functools.lru_cache(maxsize=8)
def _placeholder(shape: tuple[int, ...], dtype: str) -> Any:
    """A typed zero array on the device for the run, standing in for an array that a kernel
    takes but does not read (no colour to fuse, no colour volume)."""
    return cuda.to_device(np.zeros(shape, dtype=dtype))


def constants_to_device(role: str, rows: np.ndarray) -> Any:
    """A frame's pose-dependent constants (a small matrix) in a pooled device array. Kernels
    read them there rather than as launch parameters, so that their launches repeat from frame
    to frame and replay as a graph (targets.cuda_graphs). The copy is queued in stream order,
    after the launches before it, without a host wait (targets.cuda.copy_up)."""
    return copy_up(pooled_array(role, rows.shape, rows.dtype), rows)


def volume_placement(volume: FastTsdfVolume) -> Any:
    """Where the moving volume is: its buffer offset (row 0, in cells) and its origin (row 1,
    metres) as a (2, 3) float64 device array that integration and the raycast read. A shift
    changes what is in it, not the kernels' arguments, so their launches go on repeating and
    replaying as graphs (targets.cuda_graphs) through shifts. Copied up when a shift changed it
    (copy_up, in stream order)."""
    rows = np.array([volume.offsets(), volume.origin], dtype=np.float64)
    kept = volume.device_placement
    if kept is None or not np.array_equal(kept[0], rows):
        device = cuda.device_array((2, 3), np.float64) if kept is None else kept[1]
        volume.device_placement = (rows, copy_up(device, rows))
    return volume.device_placement[1]


def largest_depth(depth: Any) -> Any:
    """The largest valid depth of a device depth map as a (1,) device array (0 without any)."""
    largest = pooled_array("largest depth", (1,), np.float32)
    _largest_depth_into(largest, depth)
    return largest


def _largest_depth_into(largest: Any, depth: Any) -> None:
    _fill_kernel[1, 1](largest, 0)
    _max_depth_kernel[grid_2d(*depth.shape), BLOCK_2D](depth, largest)


def volume_reach(volume: FastTsdfVolume, pose: np.ndarray) -> float:
    """The largest distance from the camera centre to a voxel centre of the volume (at a corner
    of the box of voxel centres, the farthest point of a box from any point): no voxel lies
    farther along the optical axis, so a frustum box to this depth holds every voxel that any
    frame seen from `pose` can update."""
    first = np.asarray(volume.origin, dtype=np.float64) - pose[:3, 3]
    last = first + volume.voxel_size * (volume.resolution - 1)
    farthest = np.maximum(np.abs(first), np.abs(last))  # per axis, the farther face
    return float(np.linalg.norm(farthest)) + volume.voxel_size


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


@segment
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
    # The box bounds the frustum to the volume's far corner, not to the frame's largest depth
    # (which only the device knows without a wait). The result is the same voxel for voxel:
    # each voxel's update depends on that voxel and the images only, and every voxel the frame
    # updates has z <= largest depth + mu (|p_c| <= lambda D + mu), so it lies inside both this
    # box and the frustum box of the largest depth. The voxels between the two get no update
    # (fuse_voxel's sdf test); each thread skips most of them by bounding its column with the
    # largest depth read on the device (_column_span).
    box = frustum_box(volume, volume_reach(volume, pose), pose, camera)
    if box is None:
        return
    d_depth = to_device(depth, np.float32)
    largest = pooled_array("largest depth", (1,), np.float32)
    integrate_in_box(volume, d_depth, pose, camera, colour, colour_weights, box, largest)


def frame_constants(volume: FastTsdfVolume, pose: np.ndarray, box: tuple) -> Any:
    """The integration kernel's per-frame constants on the device: (6, 3) float32 with the
    voxel steps (camera_frame_steps, rows 0-2), the base (row 3) and the box [lo, hi) (rows
    4-5; voxel indices, exact in float32)."""
    base, steps = camera_frame_steps(volume, pose)
    lo, hi = index_box(box)
    rows = np.vstack([steps, base, lo, hi]).astype(np.float32)
    return constants_to_device("integration constants", rows)


def integrate_in_box(
    volume: FastTsdfVolume,
    depth: Any,
    pose: np.ndarray,
    camera: Intrinsics,
    colour: Any,
    colour_weights: Any,
    box: tuple[np.ndarray, np.ndarray],
    largest: Any = None,
) -> None:
    """integrate's fusion of a device depth map over the voxel index box [lo, hi) = `box`,
    each column bounded by z <= the frame's largest depth + mu where `largest` (a (1,) float32
    device array, which receives that depth) is given; None visits every voxel of the box (what
    the tests compare with). The copies up come first; the launches are a signed segment
    (targets.cuda_graphs.signed) of their arguments, which with graphs on replays without this
    Python once its graph exists."""
    placement, constants = volume_placement(volume), frame_constants(volume, pose, box)
    ray_distance = pooled_array("ray distance", (camera.height * camera.width + 1,), np.float32)
    fuse_colour, colour, colour_weights, colour_volume = _colour_arguments(
        volume, depth, colour, colour_weights
    )
    default_weights = fuse_colour and colour_weights is None
    if default_weights:
        colour_weights = pooled_array("colour weights", (depth.size,), np.float32)
    bounded = largest is not None
    fusion = (
        volume.tsdf_weight,
        colour_volume,
        placement,
        constants,
        largest if bounded else _placeholder((1,), "float32"),
        bounded,
        tuple(projection_constants(camera)),
        image_size(camera),
        ray_distance,
        fusion_limits(volume),
        colour,
        colour_weights,
        fuse_colour,
    )
    launches = (depth, pinhole(camera), largest, ray_distance, default_weights, fusion)
    signed("fusion", launches, lambda: _fuse(*launches))


def _fuse(
    depth: Any, camera: tuple, largest: Any, ray_distance: Any, default_weights: bool, fusion: tuple
) -> None:
    """integrate_in_box's launches: the largest depth where the columns are bounded by it,
    each pixel's ray distance, the default colour weights (fusion's 12th argument) where none
    were given, the fusion."""
    if largest is not None:
        _largest_depth_into(largest, depth)
    _ray_distance_kernel[grid_2d(*depth.shape), BLOCK_2D](depth, camera, ray_distance)
    if default_weights:
        _depth_weights_kernel[grid_2d(*depth.shape), BLOCK_2D](depth, fusion[11])
    n = fusion[0].shape[0]  # the volume's resolution
    _integrate_kernel[grid_2d(n, n), BLOCK_2D](*fusion)  # x: k (contiguous in memory), y: j


def _colour_arguments(
    volume: FastTsdfVolume, depth: Any, colour: Any, colour_weights: Any
) -> tuple[bool, Any, Any, Any]:
    """tsdf.volume.colour_inputs on the device without a host wait: (fuse_colour, colour (H W,
    3) uint8, colour weights (H W) float32 or None where they default to 1 where the float32
    depth is > 0 (a kernel makes them; where a wider input depth is > 0 but not its float32,
    the ray distance is -inf and no voxel reads the weight), colour volume), placeholders kept
    on the device for the run."""
    colour_volume = volume.colour
    if colour_volume is None:
        colour_volume = _placeholder((1, 1, 1, 4), "uint8")
    if colour is None or volume.colour is None:
        return False, _placeholder((1, 3), "uint8"), _placeholder((1,), "float32"), colour_volume
    colour = to_device(colour, np.uint8).reshape(-1, 3)
    if colour_weights is not None:
        colour_weights = to_device(colour_weights, np.float32).reshape(-1)
    return True, colour, colour_weights, colour_volume


def sample_tsdf(volume: FastTsdfVolume, coordinates: Any) -> Any:
    """Trilinear TSDF over observed voxels at continuous voxel coordinates (M, 3); NaN where
    none of the 8 is observed or outside the grid (kintinuous_ref.tsdf.sample_tsdf)."""
    d_coordinates = to_device(coordinates, np.float64)
    out = cuda.device_array(d_coordinates.shape[0], dtype=np.float64)
    _sample_kernel[grid_1d(out.shape[0]), BLOCK_1D](
        volume.tsdf_weight, *volume.offsets(), d_coordinates, out
    )
    return like_input(out, coordinates)
