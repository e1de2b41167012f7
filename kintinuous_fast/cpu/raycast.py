# ruff: noqa: ANN001, ANN201  (numba kernels and loops: argument types come from the call)
"""kintinuous_ref.raycast on the CPU: one ray per pixel in a prange loop around
kintinuous_fast.ops.volume, with the reference's exact brick empty-space skipping (the brick map
is built by a parallel loop over bricks that stops at the first negative voxel)."""

from __future__ import annotations

import numba
import numpy as np
from numba import prange

from kintinuous_fast._volume import FastTsdfVolume, empty_space_distance
from kintinuous_fast.ops import cpu_jit_numpy_errors
from kintinuous_fast.ops.volume import build_ops
from kintinuous_ref.camera import Intrinsics
from kintinuous_ref.raycast import STEP_FRACTION, ModelPrediction

__all__ = ["STEP_FRACTION", "ModelPrediction", "raycast"]

_ops = build_ops(cpu_jit_numpy_errors)
raycast_pixel = _ops.raycast_pixel
brick_negative = _ops.brick_negative
BRICK = 8


@numba.njit(parallel=True, cache=True, error_model="numpy")
def _negative_bricks(tsdf_weight, o0, o1, o2, out):
    b = out.shape[0]
    for index in prange(b * b * b):
        b0 = index // (b * b)
        b1 = (index // b) % b
        b2 = index % b
        out[b0, b1, b2] = brick_negative(tsdf_weight, o0, o1, o2, b0, b1, b2)


def empty_space(volume: FastTsdfVolume) -> np.ndarray:
    """kintinuous_ref.raycast._empty_space of the fast volume (brick distance map, int64)."""
    b = -(-volume.resolution // BRICK)
    negative = np.zeros((b, b, b), dtype=np.bool_)
    _negative_bricks(volume.tsdf_weight, *volume.offsets(), negative)
    return empty_space_distance(negative)


@numba.njit(parallel=True, cache=True, error_model="numpy")
def _raycast_loop(
    tsdf_weight,
    colour_volume,
    has_colour,
    o0,
    o1,
    o2,
    empty,
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
    for v in prange(vertices.shape[0]):
        for u in range(vertices.shape[1]):
            raycast_pixel(
                tsdf_weight,
                colour_volume,
                has_colour,
                o0,
                o1,
                o2,
                empty,
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
    volume: FastTsdfVolume, pose: np.ndarray, camera: Intrinsics, skip_empty: bool = True
) -> ModelPrediction:
    """Vertex, normal and colour maps of the model surface seen from `pose` (world frame);
    `skip_empty` (exact, as in the reference) jumps over bricks far from any surface."""
    shape = (camera.height, camera.width)
    vertices = np.full((*shape, 3), np.nan, dtype=np.float32)
    normals = np.full((*shape, 3), np.nan, dtype=np.float32)
    colours = np.zeros((*shape, 3), dtype=np.uint8)
    has_colour = volume.colour is not None
    colour_volume = volume.colour if has_colour else np.zeros((1, 1, 1, 4), np.uint8)
    pose = np.asarray(pose, dtype=np.float64)
    _raycast_loop(
        volume.tsdf_weight,
        colour_volume,
        has_colour,
        *volume.offsets(),
        empty_space(volume) if skip_empty else np.zeros((1, 1, 1), dtype=np.int64),
        np.array([camera.fx, camera.fy, camera.cx, camera.cy], dtype=np.float64),
        np.ascontiguousarray(pose[:3, :3]),
        np.ascontiguousarray(pose[:3, 3]),
        np.asarray(volume.origin, dtype=np.float64),
        float(volume.voxel_size),
        STEP_FRACTION * volume.truncation,
        vertices,
        normals,
        colours,
    )
    return ModelPrediction(pose=pose.copy(), vertices=vertices, normals=normals, colours=colours)
