# ruff: noqa: ANN001, ANN201  (numba kernels and loops: argument types come from the call)
"""kintinuous_ref.raycast as a CUDA kernel: one thread per pixel marching its ray through the
device volume around kintinuous_fast.raycast.ops, jumping over empty bricks with the reference's
brick distance map, which three small kernels compute on the device every frame. Only the pose
goes in, as launch parameters (a copy to the device would wait for the device's queued work).
`raycast` downloads the maps (a ModelPrediction of NumPy arrays like the reference's);
`predict_surface` leaves them on the device, where the next frame's tracking reads them."""

from __future__ import annotations

import functools
from typing import Any

import numpy as np
from numba import cuda

from kintinuous_fast.raycast import ops as raycast_ops
from kintinuous_fast.targets import cuda_device_jit, to_host
from kintinuous_fast.targets.cuda import (
    BLOCK_1D,
    BLOCK_2D,
    grid_1d,
    grid_2d,
    kernel,
    pooled_array,
)
from kintinuous_fast.targets.cuda_graphs import segment, signed
from kintinuous_fast.tsdf import voxel
from kintinuous_fast.tsdf.cuda import constants_to_device, volume_placement
from kintinuous_fast.tsdf.volume import FastTsdfVolume, view_constants
from kintinuous_fast.tsdf.voxel import BRICK
from kintinuous_ref.camera import Intrinsics
from kintinuous_ref.raycast import STEP_FRACTION, ModelPrediction, check_stride

__all__ = [
    "STEP_FRACTION",
    "ModelPrediction",
    "check_stride",
    "empty_space",
    "predict_surface",
    "raycast",
]

_voxels = voxel.build_ops(cuda_device_jit())
raycast_pixel = raycast_ops.build_ops(cuda_device_jit(), voxels=_voxels).raycast_pixel
count_negative = _voxels.count_negative


# Larger than any chessboard distance between bricks: "no negative brick along this axis yet".
_FAR = 1 << 30


@functools.lru_cache(maxsize=1)
def _map_that_skips_nothing() -> Any:
    """A (1, 1, 1) distance map of 0 on the device (kept for the run): as march_ray's fine map,
    the brick map decides every step (a jump from distance FINE_LEVEL_BELOW on, else a
    sample); as both maps, every sample is taken (the plain march, whose answer the exact
    skipping returns too)."""
    return cuda.to_device(np.zeros((1, 1, 1), dtype=np.uint8))


@functools.lru_cache(maxsize=1)
def _no_colour_volume() -> Any:
    """A (1, 1, 1, 4) colour volume of 0 on the device (kept for the run), which the kernel
    takes but does not read when it casts no colour."""
    return cuda.to_device(np.zeros((1, 1, 1, 4), dtype=np.uint8))


def empty_space(volume: FastTsdfVolume) -> Any:
    """kintinuous_ref.raycast.empty_space of the device volume, on the device (int64 brick
    distances): one thread per brick marks those holding an observed negative voxel, then the
    chessboard distance to them, one axis at a time (the max-norm distance is separable), less
    the one brick by which the reference grows them."""
    distance, scratch = _empty_space_buffers(volume)
    _empty_space_into(distance, scratch, volume.tsdf_weight, volume_placement(volume))
    return distance


def _empty_space_buffers(volume: FastTsdfVolume) -> tuple[Any, Any]:
    """(brick distances, scratch) for empty_space."""
    bricks = -(-volume.resolution // BRICK)
    distance = pooled_array("empty space", (bricks,) * 3, np.int64)
    return distance, pooled_array("empty space", (bricks,) * 3, np.int64)


def _empty_space_into(distance: Any, scratch: Any, tsdf_weight: Any, placement: Any) -> None:
    blocks = grid_1d(distance.size)
    _negative_brick_kernel[blocks, BLOCK_1D](tsdf_weight, placement, distance)
    for axis in range(3):
        source, target = (distance, scratch) if axis % 2 == 0 else (scratch, distance)
        _axis_distance_kernel[blocks, BLOCK_1D](source, target, axis)
    _grown_distance_kernel[blocks, BLOCK_1D](scratch, distance)  # three passes ended in scratch


@kernel
def _negative_brick_kernel(tsdf_weight, placement, distance):
    """distance[b] = 0 where logical brick b holds an observed negative voxel, else _FAR (the
    buffer offset read from `placement`, tsdf.cuda.volume_placement)."""
    o0, o1, o2 = int(placement[0, 0]), int(placement[0, 1]), int(placement[0, 2])
    bricks = distance.shape[0]
    index = cuda.grid(1)
    if index >= bricks**3:
        return
    b0, rest = index // (bricks * bricks), index % (bricks * bricks)
    b1, b2 = rest // bricks, rest % bricks
    found = count_negative(tsdf_weight, o0, o1, o2, b0, b1, b2, BRICK) > 0
    distance[b0, b1, b2] = 0 if found else _FAR


@kernel
def _axis_distance_kernel(source, target, axis):
    """target[x] = min over y on x's line along `axis` of max(|x - y|, source[y]): one pass of
    the separable chessboard distance."""
    bricks = source.shape[0]
    index = cuda.grid(1)
    if index >= bricks**3:
        return
    x = (index // (bricks * bricks), (index // bricks) % bricks, index % bricks)
    best = _FAR
    for y in range(bricks):
        offset = abs(y - x[axis])
        if axis == 0:
            value = source[y, x[1], x[2]]
        elif axis == 1:
            value = source[x[0], y, x[2]]
        else:
            value = source[x[0], x[1], y]
        best = min(best, max(offset, value))
    target[x[0], x[1], x[2]] = best


@kernel
def _grown_distance_kernel(distance, out):
    """The distance to the negative bricks grown by one brick: one less (not below 0); 2 B
    everywhere when there are none (kintinuous_ref.raycast.empty_space's convention)."""
    bricks = distance.shape[0]
    index = cuda.grid(1)
    if index >= bricks**3:
        return
    b0, b1, b2 = index // (bricks * bricks), (index // bricks) % bricks, index % bricks
    d = distance[b0, b1, b2]
    out[b0, b1, b2] = 2 * bricks if d >= _FAR else max(d - 1, 0)


@kernel
def _clear_kernel(vertices, normals, colours):
    u, v = cuda.grid(2)
    if v < vertices.shape[0] and u < vertices.shape[1]:
        for c in range(3):
            vertices[v, u, c] = np.nan
            normals[v, u, c] = np.nan
            colours[v, u, c] = 0


@kernel
def _raycast_kernel(
    tsdf_weight,
    colour_volume,
    has_colour,
    placement,
    empty,
    fine_distance,
    camera,
    pose,
    voxel_size,
    step,
    vertices,
    normals,
    colours,
    stride,
):
    # one thread per pixel cast: (u, v) multiples of the stride; `pose` (4, 3) float64: the
    # rotation (rows 0-2) and the camera centre (row 3), read from device memory, as are the
    # volume's buffer offset and origin (`placement`, tsdf.cuda.volume_placement)
    rotation, origin = pose, (pose[3, 0], pose[3, 1], pose[3, 2])
    offsets = (int(placement[0, 0]), int(placement[0, 1]), int(placement[0, 2]))
    volume_origin = (placement[1, 0], placement[1, 1], placement[1, 2])
    cast_u, cast_v = cuda.grid(2)
    u, v = cast_u * stride, cast_v * stride
    if v < vertices.shape[0] and u < vertices.shape[1]:
        raycast_pixel(
            tsdf_weight,
            colour_volume,
            has_colour,
            offsets,
            empty,
            fine_distance,
            (u, v),
            camera,
            rotation,
            origin,
            volume_origin,
            voxel_size,
            step,
            vertices,
            normals,
            colours,
            0.0,
        )


def raycast(
    volume: FastTsdfVolume,
    pose: np.ndarray,
    camera: Intrinsics,
    skip_empty: bool = True,
    colour: bool = True,
    stride: int = 1,
) -> ModelPrediction:
    """Vertex, normal and colour maps of the model surface seen from `pose` (world frame), on the
    host. `skip_empty` jumps over bricks far from any surface with the reference's exact brick
    distance map (empty_space, computed on the device); `colour` False leaves the colour map
    black; `stride` > 1 casts only the pixels whose u and v are multiples of it
    (kintinuous_ref.raycast.raycast)."""
    maps = _cast(volume, pose, camera, skip_empty, colour, stride)
    return ModelPrediction(
        pose=maps.pose,
        vertices=to_host(maps.vertices),
        normals=to_host(maps.normals),
        colours=to_host(maps.colours),
    )


@segment
def predict_surface(
    volume: FastTsdfVolume, pose: np.ndarray, camera: Intrinsics, stride: int = 1
) -> ModelPrediction:
    """The model prediction the next frame tracks against, its maps left in device memory
    (kintinuous_ref.raycast.predict_surface: vertices and normals, no colour)."""
    return _cast(volume, pose, camera, skip_empty=True, colour=False, stride=stride)


def _cast(
    volume: FastTsdfVolume,
    pose: np.ndarray,
    camera: Intrinsics,
    skip_empty: bool,
    colour: bool,
    stride: int,
) -> ModelPrediction:
    """raycast's maps as device arrays. The buffers and the pose's copy up come first; the
    launches are a signed segment (targets.cuda_graphs.signed) of their arguments."""
    check_stride(stride)
    shape = (camera.height, camera.width)
    vertices = pooled_array("raycast", (*shape, 3), np.float32)
    normals = pooled_array("raycast", (*shape, 3), np.float32)
    colours = pooled_array("raycast", (*shape, 3), np.uint8)
    has_colour = colour and volume.colour is not None
    placement = volume_placement(volume)
    pose = np.asarray(pose, dtype=np.float64)
    # the volume's origin (changed by a shift) is read from volume_placement, the pose from a
    # device matrix (it changes every frame); the intrinsics are fixed for the run
    intrinsics, rotation, origin, _, voxel_size = view_constants(volume, pose, camera)
    empty = _empty_space_buffers(volume) if skip_empty else None
    cast = (
        volume.tsdf_weight,
        volume.colour if has_colour else _no_colour_volume(),
        has_colour,
        placement,
        _map_that_skips_nothing() if empty is None else empty[0],
        _map_that_skips_nothing(),  # no finer level
        tuple(float(x) for x in intrinsics),
        constants_to_device("raycast pose", np.vstack([rotation, origin])),
        voxel_size,
        STEP_FRACTION * volume.truncation,
        vertices,
        normals,
        colours,
        int(stride),
    )
    signed("raycast", (empty, cast), lambda: _launch_cast(empty, cast))
    return ModelPrediction(pose=pose.copy(), vertices=vertices, normals=normals, colours=colours)


def _launch_cast(empty: tuple | None, cast: tuple) -> None:
    """_cast's launches: the cleared maps where pixels are left out (a stride above 1: the
    pixels cast are all written), the brick distances where empty space is skipped, the rays."""
    tsdf_weight, placement, (vertices, normals, colours), stride = (
        cast[0], cast[3], cast[10:13], cast[13],
    )  # fmt: skip
    shape = vertices.shape[:2]
    if stride > 1:
        _clear_kernel[grid_2d(*shape), BLOCK_2D](vertices, normals, colours)
    if empty is not None:
        _empty_space_into(*empty, tsdf_weight, placement)
    cast_grid = grid_2d(-(-shape[0] // stride), -(-shape[1] // stride))
    _raycast_kernel[cast_grid, BLOCK_2D](*cast)
