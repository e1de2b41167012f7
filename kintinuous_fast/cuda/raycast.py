# ruff: noqa: ANN001, ANN201  (numba kernels and loops: argument types come from the call)
"""kintinuous_ref.raycast as a CUDA kernel: one thread per pixel marching its ray through the
device volume around kintinuous_fast.ops.volume. Only the pose goes in; the maps are device
arrays (downloaded when `download` is True, the default, for a ModelPrediction of NumPy arrays
like the reference's)."""

from __future__ import annotations

from typing import Any

import numpy as np
from numba import cuda

from kintinuous_fast._volume import FastTsdfVolume
from kintinuous_fast.cuda import BLOCK_2D, grid_2d
from kintinuous_fast.ops import cuda_device_jit
from kintinuous_fast.ops.volume import build_ops
from kintinuous_ref.camera import Intrinsics
from kintinuous_ref.raycast import STEP_FRACTION, ModelPrediction

__all__ = ["STEP_FRACTION", "ModelPrediction", "raycast"]

_ops = build_ops(cuda_device_jit())
raycast_pixel = _ops.raycast_pixel


_PLAIN_MARCH: list = []


def _plain_march_maps() -> tuple[Any, Any]:
    """A (1, 1, 1) brick map of 0 and a (1, 1, 1) fine map of 1 on the device: march_ray then
    samples every step (the plain march, whose answer the reference's exact skipping returns
    too)."""
    if not _PLAIN_MARCH:
        _PLAIN_MARCH.append(cuda.to_device(np.zeros((1, 1, 1), dtype=np.int64)))
        _PLAIN_MARCH.append(cuda.to_device(np.ones((1, 1, 1), dtype=np.uint8)))
    return _PLAIN_MARCH[0], _PLAIN_MARCH[1]


@cuda.jit
def _clear_kernel(vertices, normals, colours):
    u, v = cuda.grid(2)
    if v < vertices.shape[0] and u < vertices.shape[1]:
        for c in range(3):
            vertices[v, u, c] = np.nan
            normals[v, u, c] = np.nan
            colours[v, u, c] = 0


@cuda.jit
def _raycast_kernel(
    tsdf_weight,
    colour_volume,
    has_colour,
    o0,
    o1,
    o2,
    empty,
    near,
    camera,
    rotation,
    origin,
    volume_origin,
    voxel_size,
    step,
    vertices,
    normals,
    colours,
):
    u, v = cuda.grid(2)
    if v < vertices.shape[0] and u < vertices.shape[1]:
        raycast_pixel(
            tsdf_weight,
            colour_volume,
            has_colour,
            o0,
            o1,
            o2,
            empty,
            near,
            u,
            v,
            camera,
            rotation,
            origin,
            volume_origin,
            voxel_size,
            step,
            vertices,
            normals,
            colours,
        )


def raycast(
    volume: FastTsdfVolume,
    pose: np.ndarray,
    camera: Intrinsics,
    skip_empty: bool = True,
    colour: bool = True,
    download: bool = True,
) -> ModelPrediction:
    """Vertex, normal and colour maps of the model surface seen from `pose` (world frame).
    `skip_empty` is accepted for the reference's signature (its skipping is exact); `colour`
    False leaves the colour map black (kintinuous_ref.raycast.raycast)."""
    shape = (camera.height, camera.width)
    vertices = cuda.device_array((*shape, 3), dtype=np.float32)
    normals = cuda.device_array((*shape, 3), dtype=np.float32)
    colours = cuda.device_array((*shape, 3), dtype=np.uint8)
    grid = grid_2d(*shape)
    _clear_kernel[grid, BLOCK_2D](vertices, normals, colours)
    has_colour = colour and volume.colour is not None
    colour_volume = (
        volume.colour if has_colour else cuda.to_device(np.zeros((1, 1, 1, 4), np.uint8))
    )
    pose = np.asarray(pose, dtype=np.float64)
    _raycast_kernel[grid, BLOCK_2D](
        volume.tsdf_weight,
        colour_volume,
        has_colour,
        *volume.offsets(),
        *_plain_march_maps(),
        cuda.to_device(np.array([camera.fx, camera.fy, camera.cx, camera.cy], dtype=np.float64)),
        cuda.to_device(np.ascontiguousarray(pose[:3, :3])),
        cuda.to_device(np.ascontiguousarray(pose[:3, 3])),
        cuda.to_device(np.asarray(volume.origin, dtype=np.float64)),
        float(volume.voxel_size),
        STEP_FRACTION * volume.truncation,
        vertices,
        normals,
        colours,
    )
    if not download:
        return ModelPrediction(
            pose=pose.copy(), vertices=vertices, normals=normals, colours=colours
        )
    return ModelPrediction(
        pose=pose.copy(),
        vertices=vertices.copy_to_host(),
        normals=normals.copy_to_host(),
        colours=colours.copy_to_host(),
    )
