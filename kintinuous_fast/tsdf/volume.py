"""The fast backends' TSDF + colour volume (8 bytes per voxel) and the host-side per-frame set-up
shared by the cpu and cuda integration and raycasting (their per-voxel and per-ray maths:
kintinuous_fast.tsdf.voxel, tsdf.ops and raycast.ops), its conversions to and from the
reference's TsdfVolume, and the moving volume's view of it (SlabView)."""

from __future__ import annotations

import functools
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from kintinuous_fast.targets import to_host
from kintinuous_fast.tsdf.voxel import TSDF_SCALE
from kintinuous_ref.camera import Intrinsics
from kintinuous_ref.config import VolumeConfig
from kintinuous_ref.tsdf import (
    TsdfVolume,
    VoxelGrid,
    available_memory_bytes,
    refuse_if_too_big,
    volume_origin,
)

BYTES_TSDF = 4  # int16 TSDF + int16 weight
BYTES_COLOUR = 4  # uint8 R, G, B + uint8 colour weight


@dataclass
class NegativeMasks:
    """Per logical fine brick (FINE^3 voxels) a bit mask of its observed voxels with negative
    TSDF (tsdf.voxel.fine_voxel_bit), for the cpu raycast's empty-space maps. Integration keeps
    them up to date; they describe the logical bricks of the buffer offset they were taken at,
    so a shift (or clearing cells) makes them stale and they are taken again from the volume
    when next needed."""

    masks: np.ndarray  # (M, M, M) uint8, M = ceil(N / FINE)
    offset: tuple[int, int, int]


@dataclass
class FastTsdfVolume(VoxelGrid):
    """kintinuous_ref.tsdf.TsdfVolume in 8 bytes per voxel, on the host (cpu) or device (cuda).

    tsdf_weight[..., 0] = round(F * 32767), tsdf_weight[..., 1] = W; colour[..., :3] = RGB,
    colour[..., 3] = the colour weight rounded to an integer (>= 1 once coloured). Indexed
    [x, y, z] like the reference; voxel (i, j, k) is centred at origin + voxel_size (i, j, k).
    """

    tsdf_weight: Any  # (N, N, N, 2) int16
    colour: Any | None  # (N, N, N, 4) uint8, or None without a colour volume
    origin: np.ndarray
    voxel_size: float
    truncation: float
    max_weight: float
    colour_max_weight: float = 255.0
    # (3,) int in [0, N): array cell of logical voxel (0, 0, 0), the cyclical buffer of the
    # moving volume (kintinuous_ref.tsdf.TsdfVolume.offset); zero until the volume shifts
    offset: np.ndarray = field(default_factory=lambda: np.zeros(3, dtype=np.int64))
    # cpu backend only: the negative-voxel masks (NegativeMasks) or None when not known;
    # whatever writes tsdf_weight other than integration must call forget_negative_masks()
    negative_masks: NegativeMasks | None = field(default=None, repr=False, compare=False)
    # cuda backend only: (the rows, the device array) of tsdf.cuda.volume_placement, or None
    device_placement: tuple | None = field(default=None, repr=False, compare=False)

    @property
    def resolution(self) -> int:
        return self.tsdf_weight.shape[0]

    def offsets(self) -> tuple[int, int, int]:
        """The offset as three Python ints (o0, o1, o2), as the kernels take it."""
        o = np.asarray(self.offset, dtype=np.int64) % self.resolution
        return int(o[0]), int(o[1]), int(o[2])

    def current_negative_masks(self) -> np.ndarray | None:
        """The negative-voxel masks if they hold for the current offset, else None."""
        known = self.negative_masks
        if known is None or known.offset != self.offsets():
            return None
        return known.masks

    def forget_negative_masks(self) -> None:
        self.negative_masks = None


def memory_bytes(config: VolumeConfig) -> int:
    """Memory of a fast volume: 4 bytes per voxel, 8 with colour (1 GiB at 512^3)."""
    return (BYTES_TSDF + (BYTES_COLOUR if config.colour else 0)) * config.resolution**3


def check_volume_memory(config: VolumeConfig, available: int | None = None) -> None:
    """Refuse, in one line, a fast volume (memory_bytes) that does not fit in `available`
    bytes: host memory by default (the cpu backend's check_volume_config), the GPU's free
    memory where the cuda backend passes it. The config's own fields were checked when it was
    made (VolumeConfig.__post_init__)."""
    available = available_memory_bytes() if available is None else available
    # Headroom for the rest of the pipeline: the fast loops update voxels in place, where the
    # reference's NumPy integration makes slab-sized temporaries (its headroom: 1 GiB).
    refuse_if_too_big(config, memory_bytes(config), available, 256 << 20)


def volume_header(
    config: VolumeConfig, first_pose: np.ndarray, colour_max_weight: float
) -> dict[str, Any]:
    """The scalar fields of a new volume placed for the first pose (as make_volume does)."""
    return {
        "origin": volume_origin(np.asarray(first_pose, dtype=np.float64), config),
        "voxel_size": config.voxel_size,
        "truncation": config.truncation,
        "max_weight": config.max_weight,
        "colour_max_weight": colour_max_weight,
    }


def to_reference_volume(volume: FastTsdfVolume) -> TsdfVolume:
    """A float32 kintinuous_ref TsdfVolume with the fast volume's (dequantised) values, on the
    host: for meshing, and for comparing a fast volume with the reference."""
    packed = np.asarray(to_host(volume.tsdf_weight))
    colour = to_host(volume.colour)
    return TsdfVolume(
        tsdf=packed[..., 0].astype(np.float32) / np.float32(TSDF_SCALE),
        weight=packed[..., 1].astype(np.float32),
        colour=None if colour is None else colour[..., :3].astype(np.float32),
        colour_weight=None if colour is None else colour[..., 3].astype(np.float32),
        origin=np.array(volume.origin, dtype=np.float64),
        voxel_size=volume.voxel_size,
        truncation=volume.truncation,
        max_weight=volume.max_weight,
        colour_max_weight=volume.colour_max_weight,
        offset=np.array(volume.offset, dtype=np.int64),
    )


def from_reference_volume(volume: TsdfVolume) -> FastTsdfVolume:
    """A host fast volume holding a reference volume's values rounded to the stored types."""
    packed = np.empty((*volume.tsdf.shape, 2), dtype=np.int16)
    packed[..., 0] = np.clip(np.rint(volume.tsdf * TSDF_SCALE), -32767, 32767)
    packed[..., 1] = np.rint(volume.weight)
    colour = None
    if volume.colour is not None:
        colour = np.empty((*volume.tsdf.shape, 4), dtype=np.uint8)
        colour[..., :3] = np.clip(np.rint(volume.colour), 0, 255)
        weight = np.clip(np.rint(volume.colour_weight), 0, 255)
        colour[..., 3] = np.where(volume.colour_weight > 0, np.maximum(weight, 1), 0)
    return FastTsdfVolume(
        tsdf_weight=packed,
        colour=colour,
        origin=np.array(volume.origin, dtype=np.float64),
        voxel_size=volume.voxel_size,
        truncation=volume.truncation,
        max_weight=volume.max_weight,
        colour_max_weight=volume.colour_max_weight,
        offset=np.array(getattr(volume, "offset", np.zeros(3)), dtype=np.int64),
    )


# ----------------------------------------------------------------------------------------------
# Per-frame set-up of integration


def camera_frame_steps(volume: FastTsdfVolume, pose: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(base, steps) float32 with p_c(i, j, k) = base + i steps[0] + j steps[1] + k steps[2]:
    the camera-frame position of voxel (i, j, k), computed as the reference does."""
    rotation_t = pose[:3, :3].T
    base = (rotation_t @ (volume.origin - pose[:3, 3])).astype(np.float32)
    steps = np.ascontiguousarray((volume.voxel_size * rotation_t).T.astype(np.float32))
    return base, steps


def colour_inputs(
    volume: FastTsdfVolume,
    depth: Any,
    colour: Any,
    colour_weights: Any,
    convert: Callable[[Any, Any], Any],
) -> tuple[bool, Any, Any, Any]:
    """(fuse_colour, colour (H W, 3) uint8, colour weights (H W) float32, colour volume): the
    integration kernels' colour arguments, each made the target's array by `convert(array,
    dtype)` (np.ascontiguousarray on the cpu, targets.cuda.to_device on cuda). Colour weights
    default to 1 where there is depth. Without colour to fuse, or without a colour volume,
    typed placeholders that the kernels never read stand in."""
    fuse_colour = colour is not None and volume.colour is not None
    if fuse_colour:
        colour = convert(colour, np.uint8).reshape(-1, 3)
        if colour_weights is None:
            colour_weights = (np.asarray(to_host(depth)) > 0).astype(np.float32)
        colour_weights = convert(colour_weights, np.float32).reshape(-1)
    else:
        colour = convert(np.zeros((1, 3), np.uint8), np.uint8)
        colour_weights = convert(np.zeros(1, np.float32), np.float32)
    colour_volume = volume.colour
    if colour_volume is None:
        colour_volume = convert(np.zeros((1, 1, 1, 4), np.uint8), np.uint8)
    return fuse_colour, colour, colour_weights, colour_volume


def projection_constants(camera: Intrinsics) -> np.ndarray:
    """fx, fy, cx, cy as float32: NumPy 2 evaluates the reference's fx * x / z + cx in float32."""
    return np.array([camera.fx, camera.fy, camera.cx, camera.cy], dtype=np.float32)


def image_size(camera: Intrinsics) -> tuple[int, int]:
    """(W, H): the image size a kernel takes as one argument."""
    return int(camera.width), int(camera.height)


def index_box(box: tuple[np.ndarray, np.ndarray]) -> tuple[tuple[int, ...], tuple[int, ...]]:
    """frustum_box's [lo, hi) as two tuples of three ints (one kernel argument)."""
    return tuple(int(x) for x in box[0]), tuple(int(x) for x in box[1])


def fusion_limits(volume: FastTsdfVolume) -> tuple[np.float32, np.float32, np.float32]:
    """(mu, the weight cap, the colour weight cap) in float32, the reference's precision:
    the limits of tsdf.ops.fuse_voxel, one kernel argument."""
    return (
        np.float32(volume.truncation),
        np.float32(volume.max_weight),
        np.float32(volume.colour_max_weight),
    )


def view_constants(volume: FastTsdfVolume, pose: np.ndarray, camera: Intrinsics) -> tuple:
    """(camera as float64 fx, fy, cx, cy; rotation; origin; volume origin; voxel size): the
    view's arguments of the raycast's loops and kernel, on the host."""
    return (
        np.array([camera.fx, camera.fy, camera.cx, camera.cy], dtype=np.float64),
        np.ascontiguousarray(pose[:3, :3], dtype=np.float64),
        np.ascontiguousarray(pose[:3, 3], dtype=np.float64),
        np.asarray(volume.origin, dtype=np.float64),
        float(volume.voxel_size),
    )


@functools.lru_cache(maxsize=16)
def _frustum_rays(camera: Intrinsics) -> np.ndarray:
    """The camera centre (a zero ray) and the rays through the image's four outer corners at
    z = 1, (5, 3): the frustum's apex and edges, the same for every frame of a camera."""
    w, h = camera.width - 0.5, camera.height - 0.5
    corners = np.array([[-0.5, -0.5], [w, -0.5], [-0.5, h], [w, h]])
    rays = np.column_stack(
        [
            (corners[:, 0] - camera.cx) / camera.fx,
            (corners[:, 1] - camera.cy) / camera.fy,
            np.ones(4),
        ]
    )
    rays = np.vstack([np.zeros(3), rays])
    rays.flags.writeable = False  # shared by every call
    return rays


def frustum_box(
    volume: FastTsdfVolume, max_depth: float, pose: np.ndarray, camera: Intrinsics
) -> tuple[np.ndarray, np.ndarray] | None:
    """Voxel index box [lo, hi) holding every voxel this frame can update, or None.

    A voxel is updated only if it projects into the image and lies no farther than the largest
    depth + truncation along z, i.e. inside the pyramid of the camera centre and the image's
    corners at that depth; the box bounds the pyramid (with a voxel of margin for rounding).
    """
    if not max_depth > 0:
        return None
    far = float(max_depth) + volume.truncation
    points = far * _frustum_rays(camera)
    coords = volume.world_to_voxel(points @ pose[:3, :3].T + pose[:3, 3])
    n = volume.resolution
    lo = np.clip(np.floor(coords.min(axis=0)).astype(np.int64) - 1, 0, n)
    hi = np.clip(np.ceil(coords.max(axis=0)).astype(np.int64) + 2, 0, n)
    if np.any(hi <= lo):
        return None
    return lo, hi


# ----------------------------------------------------------------------------------------------
# The moving volume's view of a fast volume


def _pieces(index: np.ndarray) -> list[tuple[int, int, int]]:
    """A wrapped range of cells (np.arange(a, b) + o) % n as (start in the output, first cell,
    length) runs of consecutive cells (at most two)."""
    breaks = np.flatnonzero(np.diff(index) != 1) + 1
    starts = np.concatenate([[0], breaks])
    stops = np.concatenate([breaks, [len(index)]])
    return [(int(s), int(index[s]), int(e - s)) for s, e in zip(starts, stops, strict=True)]


def _blocks(cells: tuple) -> list[tuple[tuple, tuple]]:
    """(output slices, array slices) of the contiguous blocks that make up TsdfVolume.cells'
    index (plain slices: one block; np.ix_ arrays of wrapped ranges: up to 8)."""
    if all(isinstance(c, slice) for c in cells):
        return [(tuple(slice(0, c.stop - c.start) for c in cells), cells)]
    per_axis = [_pieces(np.asarray(c).reshape(-1)) for c in cells]
    blocks = []
    for a in per_axis[0]:
        for b in per_axis[1]:
            for c in per_axis[2]:
                out = tuple(slice(p[0], p[0] + p[2]) for p in (a, b, c))
                src = tuple(slice(p[1], p[1] + p[2]) for p in (a, b, c))
                blocks.append((out, src))
    return blocks


def _shape(cells: tuple) -> tuple[int, int, int]:
    return tuple(c.stop - c.start if isinstance(c, slice) else np.asarray(c).size for c in cells)


class _Field:
    """One dequantised field of a fast volume as kintinuous_ref.moving_volume reads and clears
    it: `field[cells]` gives a float32 host copy of the cells (downloading only those blocks
    from a GPU), `field[cells] = 0` clears them."""

    def __init__(self, volume: FastTsdfVolume, name: str) -> None:
        self.volume, self.name = volume, name

    def _source(self) -> tuple[Any, Any]:
        if self.name in ("tsdf", "weight"):
            return self.volume.tsdf_weight, 0 if self.name == "tsdf" else 1
        return self.volume.colour, slice(0, 3) if self.name == "colour" else 3

    def __getitem__(self, cells: tuple) -> np.ndarray:
        array, channel = self._source()
        shape = _shape(cells)
        extra = (3,) if self.name == "colour" else ()
        out = np.empty((*shape, *extra), dtype=np.float32)
        for out_index, src in _blocks(cells):
            out[out_index] = to_host(array[src])[..., channel]
        if self.name == "tsdf":
            out /= np.float32(TSDF_SCALE)
        return out

    def __setitem__(self, cells: tuple, value: float) -> None:
        if value != 0:
            raise ValueError("a fast volume's cells can only be cleared (set to 0)")
        array, _ = self._source()  # clearing: every channel of the voxel
        self.volume.forget_negative_masks()
        for _, src in _blocks(cells):
            # A device array assigns the scalar by a kernel, strided blocks too (a block of a
            # box that wraps along y or z is not contiguous, and copy_to_device refuses it).
            array[src] = 0


class SlabView:
    """A FastTsdfVolume seen through kintinuous_ref.tsdf.TsdfVolume's interface as far as the
    moving volume (kintinuous_ref.moving_volume) uses it: resolution, voxel_size, origin and
    offset (shared with the volume: shifting the view shifts the volume), cells(), and the four
    fields, read and cleared per box of cells. The cpu mesh stage reads a slice's box through
    the fields; the cuda one meshes the view's volume on the device (mesh/cuda.py mesh_box),
    so nothing of the box crosses from a GPU, and clearing runs there too."""

    def __init__(self, volume: FastTsdfVolume) -> None:
        self.fast = volume
        self.tsdf = _Field(volume, "tsdf")
        self.weight = _Field(volume, "weight")
        has_colour = volume.colour is not None
        self.colour = _Field(volume, "colour") if has_colour else None
        self.colour_weight = _Field(volume, "colour_weight") if has_colour else None

    resolution = property(lambda self: self.fast.resolution)
    voxel_size = property(lambda self: self.fast.voxel_size)
    truncation = property(lambda self: self.fast.truncation)
    size = property(lambda self: self.fast.size)
    shifted = property(lambda self: self.fast.shifted)

    @property
    def offset(self) -> np.ndarray:
        return self.fast.offset

    @property
    def origin(self) -> np.ndarray:
        return self.fast.origin

    @origin.setter
    def origin(self, value: np.ndarray) -> None:
        self.fast.origin = np.asarray(value, dtype=np.float64)

    def cells(self, start: tuple[int, int, int], stop: tuple[int, int, int]) -> tuple:
        return TsdfVolume.cells(self, start, stop)  # type: ignore[arg-type]

    def world_to_voxel(self, points: np.ndarray) -> np.ndarray:
        return self.fast.world_to_voxel(points)

    def voxel_to_world(self, coordinates: np.ndarray) -> np.ndarray:
        return self.fast.voxel_to_world(coordinates)


def slab_view(volume: FastTsdfVolume) -> SlabView:
    """The moving volume's view of a fast volume (SlabView)."""
    return SlabView(volume)
