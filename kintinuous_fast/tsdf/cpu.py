# ruff: noqa: ANN001, ANN201  (numba kernels and loops: argument types come from the call)
"""kintinuous_ref.tsdf on the CPU: integration as a loop over voxel slabs (on all threads) around
kintinuous_fast.tsdf.ops, into the 8-byte-per-voxel FastTsdfVolume (kintinuous_fast.tsdf.volume).
"""

from __future__ import annotations

import numba
import numpy as np

from kintinuous_fast.targets import cpu_jit, cpu_jit_numpy_errors, pinhole
from kintinuous_fast.targets.cache import register_slowest
from kintinuous_fast.targets.cpu import (
    claim_slot,
    claimed_items,
    parallel_part,
    prefetch_cell,
    run_parallel,
    threads,
)
from kintinuous_fast.tsdf import ops as integration
from kintinuous_fast.tsdf import voxel
from kintinuous_fast.tsdf.cpu_culling import CULL_BRICK, columns_to_visit
from kintinuous_fast.tsdf.volume import (
    FastTsdfVolume,
    NegativeMasks,
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
from kintinuous_fast.tsdf.voxel import FINE
from kintinuous_ref.camera import Intrinsics
from kintinuous_ref.config import VolumeConfig
from kintinuous_ref.tsdf import (
    VoxelGrid,
    available_memory_bytes,
    check_depth,
    corner_weights,
    refuse_if_too_big,
    trilinear,
    volume_origin,
)

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

_voxels = voxel.build_ops(cpu_jit_numpy_errors)
_ops = integration.build_ops(cpu_jit_numpy_errors, _voxels)
column_range = _ops.column_range
cell = _voxels.cell
ray_distance_pixel = _ops.ray_distance_pixel
sample_tsdf_at = _voxels.sample_tsdf_at
fine_voxel_bit = _voxels.fine_voxel_bit
project_voxel = _ops.project_voxel
voxel_norm = _ops.voxel_norm
fuse_voxel = _ops.fuse_voxel
column_start = _ops.column_start

_loop = parallel_part(error_model="numpy")
_NO_MASKS = np.zeros((1, 1, 1), dtype=np.uint8)  # typed placeholder: masks not kept


@_loop
def _ray_distance_loop(claims, parts, depth, camera, out):
    height, width = depth.shape
    for v in claimed_items(claims, height, parts):
        for u in range(width):
            out[v * width + u] = ray_distance_pixel(depth[v, u], u, v, camera)


def ray_distances(depth: np.ndarray, camera: Intrinsics) -> np.ndarray:
    """lambda D of every pixel of a float32 depth map, flat, and -inf in a last slot for "no
    pixel" (project_voxel)."""
    out = np.empty(depth.size + 1, dtype=np.float32)
    run_parallel(_ray_distance_loop, depth, pinhole(camera), out)
    out[-1] = -np.inf
    return out


@numba.njit(cache=True, error_model="numpy", inline="always")
def _integrate_slice(
    tsdf_weight,
    colour_volume,
    offsets,
    lo,
    hi,
    base,
    steps,
    intrinsics,
    image_size,
    far,
    ray_distance,
    limits,
    colour,
    colour_weights,
    fuse_colour,
    masks,
    keep_masks,
    visit,
    i,
    columns,
):
    """The voxel columns of logical slice i (see _integrate_loop), software-pipelined: column
    j is projected (_project_column) and the volume lines it will update are prefetched, then
    column j - 1, projected one step earlier, is fused; its lines have arrived meanwhile.
    `columns` = (pixels, norms, sdfs, updated): work arrays (_column_work) for two columns,
    this one and the one before."""
    o0, o1, o2 = offsets
    n = tsdf_weight.shape[0]
    pixels, norms, sdfs, updated = columns
    fi = np.float32(i)
    ci = cell(i, o0, n)
    step = (float(steps[2, 0]), float(steps[2, 1]), float(steps[2, 2]))
    for j in range(lo[1], hi[1] + 1):
        if j < hi[1]:
            this = j & 1
            px, py, pz = column_start(base, steps, fi, np.float32(j))
            start = (float(px), float(py), float(pz))
            k0, k1 = column_range(start, step, intrinsics, image_size, far, n)
            k0 = max(k0, lo[2])
            bundle = visit[i // CULL_BRICK[0], j // CULL_BRICK[1]]
            k0 = max(k0, bundle[0])
            k1 = max(min(k1, bundle[1]), k0)
            first, last = _project_column(
                (k0, k1),
                (px, py, pz),
                steps,
                intrinsics,
                image_size,
                ray_distance,
                limits[0],
                pixels[this],
                norms[this],
                sdfs[this],
            )
            cj = cell(j, o1, n)
            _prefetch_cells(tsdf_weight, ci, cj, first, last, o2, n)
            if fuse_colour:  # the lines of the few voxels near the surface are among these
                _prefetch_cells(colour_volume, ci, cj, first, last, o2, n)
            updated[this, 0], updated[this, 1] = first, last + 1
        if j > lo[1]:
            before = (j - 1) & 1
            _fuse_column(
                tsdf_weight,
                colour_volume,
                (ci, cell(j - 1, o1, n), o2),
                (i, j - 1),
                (updated[before, 0], updated[before, 1]),
                pixels[before],
                sdfs[before],
                limits,
                colour,
                colour_weights,
                fuse_colour,
                masks,
                keep_masks,
            )


@numba.njit(cache=True, error_model="numpy", inline="always")
def _project_column(
    span, start, steps, intrinsics, image_size, ray_distance, truncation, pixels, norms, sdfs
):
    """Voxels [k0, k1) = `span` of a column from camera-frame p + k a, p = `start`: pixel,
    distance and sdf, in two passes (the first vectorises: counted from 0 with a float32
    counter, as LLVM needs; the second is a gather). Returns the first and last k to update
    (sdf >= -mu), found by a scan from each end afterwards (tracking them inside the gather
    loop costs more)."""
    k0, k1 = span
    px, py, pz = start
    fk0 = np.float32(k0)
    for m in range(k1 - k0):
        fk = fk0 + np.float32(m)
        x = px + fk * steps[2, 0]
        y = py + fk * steps[2, 1]
        z = pz + fk * steps[2, 2]
        pixels[k0 + m] = project_voxel(x, y, z, intrinsics, image_size)
        norms[k0 + m] = voxel_norm(x, y, z)
    column_pixels, column_norms, column_sdfs = pixels[k0:k1], norms[k0:k1], sdfs[k0:k1]
    for m in range(k1 - k0):
        column_sdfs[m] = ray_distance[column_pixels[m]] - column_norms[m]
    first = k0
    while first < k1 and not sdfs[first] >= -truncation:
        first += 1
    last = k1 - 1
    while last >= first and not sdfs[last] >= -truncation:
        last -= 1
    return first, last


@numba.njit(cache=True, error_model="numpy", inline="always")
def _prefetch_cells(volume, ci, cj, first, last, o2, n):
    """Prefetch the lines of logical voxels first..last of column (ci, cj): 16 voxels of 4
    bytes share a 64-byte line."""
    if last < first:
        return
    for k in range(first, last + 1, 16):
        prefetch_cell(volume, ci, cj, cell(k, o2, n))
    prefetch_cell(volume, ci, cj, cell(last, o2, n))


@numba.njit(cache=True, error_model="numpy", inline="always")
def _fuse_column(
    tsdf_weight,
    colour_volume,
    column_cells,
    column,
    span,
    pixels,
    sdfs,
    limits,
    colour,
    colour_weights,
    fuse_colour,
    masks,
    keep_masks,
):
    """Pass 3: fuse_voxel on the voxels [first, end) = `span` of logical column `column` = (i, j)
    with sdf >= -mu; `column_cells` = (its array cells ci, cj, and the k offset o2)."""
    ci, cj, o2 = column_cells
    i, j = column
    first, end = span
    n = tsdf_weight.shape[0]
    truncation = limits[0]
    span_sdfs, span_pixels = sdfs[first:end], pixels[first:end]
    for m in range(end - first):
        if not span_sdfs[m] >= -truncation:
            continue
        k = first + m
        change = fuse_voxel(
            tsdf_weight,
            colour_volume,
            (ci, cj, cell(k, o2, n)),
            span_pixels[m],
            span_sdfs[m],
            limits,
            colour,
            colour_weights,
            fuse_colour,
        )
        if keep_masks and change != 0:
            bit = fine_voxel_bit(i, j, k)
            mask = masks[i // FINE, j // FINE, k // FINE]
            masks[i // FINE, j // FINE, k // FINE] = mask | bit if change > 0 else mask & ~bit


@register_slowest("tsdf")
@_loop
def _integrate_loop(
    claims,
    parts,
    tsdf_weight,
    colour_volume,
    offsets,
    box,
    base,
    steps,
    intrinsics,
    image_size,
    far,
    ray_distance,
    limits,
    colour,
    colour_weights,
    fuse_colour,
    masks,
    keep_masks,
    visit,
    work,
):
    """`box` = (lo, hi): the voxel index box [lo, hi); `far`: the farthest z to visit;
    `limits`: fuse_voxel's; `work`: _column_work's arrays, one set per thread."""
    # Voxel columns along k: only the k-range that can project into the image (column_range)
    # is visited, so the work follows the viewing pyramid, not its bounding box. Threads take
    # whole fine bricks along i, so no two threads ever change the same brick's mask.
    lo, hi = box
    low_brick = lo[0] // FINE
    slot = claim_slot(claims)
    columns = (work[0][slot], work[1][slot], work[2][slot], work[3][slot])
    for brick in claimed_items(claims, (hi[0] + FINE - 1) // FINE - low_brick, parts):
        brick += low_brick
        for i in range(max(brick * FINE, lo[0]), min((brick + 1) * FINE, hi[0])):
            _integrate_slice(
                tsdf_weight,
                colour_volume,
                offsets,
                lo,
                hi,
                base,
                steps,
                intrinsics,
                image_size,
                far,
                ray_distance,
                limits,
                colour,
                colour_weights,
                fuse_colour,
                masks,
                keep_masks,
                visit,
                i,
                columns,
            )


@_loop
def _sample_loop(claims, parts, tsdf_weight, o0, o1, o2, coordinates, out):
    for m in claimed_items(claims, coordinates.shape[0], parts):
        out[m] = sample_tsdf_at(
            tsdf_weight, o0, o1, o2, coordinates[m, 0], coordinates[m, 1], coordinates[m, 2]
        )


def check_volume_config(config: VolumeConfig) -> None:
    """Refuse, in one line, a volume (memory_bytes) that does not fit in host memory."""
    check_volume_memory(config)


def make_volume(
    config: VolumeConfig, first_pose: np.ndarray, colour_max_weight: float = 255.0
) -> FastTsdfVolume:
    """An empty volume placed for the first camera pose (all weights 0)."""
    check_volume_config(config)
    n, m = config.resolution, -(-config.resolution // FINE)
    return FastTsdfVolume(
        tsdf_weight=np.zeros((n, n, n, 2), dtype=np.int16),
        colour=np.zeros((n, n, n, 4), dtype=np.uint8) if config.colour else None,
        **volume_header(config, first_pose, colour_max_weight),
        negative_masks=NegativeMasks(np.zeros((m, m, m), dtype=np.uint8), (0, 0, 0)),
    )


@cpu_jit
def _largest_depth(depth):  # noqa: ANN001, ANN202 (numba: types from the call)
    """The largest depth of the image, 0 where none is positive (NaN never is): what
    depth[depth > 0].max() gives, in one pass that copies nothing."""
    largest = np.float32(0.0)
    for v in range(depth.shape[0]):
        for u in range(depth.shape[1]):
            if depth[v, u] > largest:
                largest = depth[v, u]
    return largest


def integrate(
    volume: FastTsdfVolume,
    depth: np.ndarray,
    pose: np.ndarray,
    camera: Intrinsics,
    colour: np.ndarray | None = None,
    colour_weights: np.ndarray | None = None,
) -> None:
    """Fuse one depth map (and optionally its colour) into the volume, in place (paper III, VI);
    the update rule is kintinuous_ref.tsdf.integrate's, rounded to the stored types."""
    check_depth(depth, camera)
    depth = np.ascontiguousarray(depth, dtype=np.float32)
    largest = float(_largest_depth(depth))
    box = frustum_box(volume, largest, pose, camera)
    if box is None:
        return
    ray_distance = ray_distances(depth, camera)
    fuse_colour, colour, colour_weights, colour_volume = colour_inputs(
        volume, depth, colour, colour_weights, np.ascontiguousarray
    )
    base, steps = camera_frame_steps(volume, pose)
    visit = columns_to_visit(volume, box, base, steps, camera, ray_distance, pose)
    masks = volume.current_negative_masks()  # kept up to date where known
    # Slabs cost different amounts: handed out dynamically, two fine bricks at a time.
    lo, hi = index_box(box)
    parts = max(1, (hi[0] - lo[0]) // (2 * FINE))
    run_parallel(
        _integrate_loop,
        volume.tsdf_weight,
        colour_volume,
        volume.offsets(),
        (lo, hi),
        base,
        steps,
        projection_constants(camera),
        image_size(camera),
        largest + float(volume.truncation),
        ray_distance,
        fusion_limits(volume),
        colour,
        colour_weights,
        fuse_colour,
        _NO_MASKS if masks is None else masks,
        masks is not None,
        visit,
        _column_work(threads(), volume.resolution),
        parts=parts,
    )


def _column_work(threads: int, n: int) -> tuple[np.ndarray, ...]:
    """_integrate_slice's work arrays for `threads` threads and n voxels a column: per thread and
    column (this one and the one before), each voxel's pixel, distance and SDF, and the
    range [first, last + 1) of voxels updated."""
    return (
        np.empty((threads, 2, n), dtype=np.uint32),
        np.empty((threads, 2, n), dtype=np.float32),
        np.empty((threads, 2, n), dtype=np.float32),
        np.zeros((threads, 2, 2), dtype=np.int64),
    )


def sample_tsdf(volume: FastTsdfVolume, coordinates: np.ndarray) -> np.ndarray:
    """Trilinear TSDF over observed voxels at continuous voxel coordinates (M, 3); NaN where
    none of the 8 is observed or outside the grid (kintinuous_ref.tsdf.sample_tsdf)."""
    coordinates = np.ascontiguousarray(coordinates, dtype=np.float64).reshape(-1, 3)
    out = np.empty(len(coordinates), dtype=np.float64)
    run_parallel(_sample_loop, volume.tsdf_weight, *volume.offsets(), coordinates, out)
    return out
