"""The fast backends' TSDF + colour volume (8 bytes per voxel) and the host-side per-frame set-up
shared by the cpu and cuda integration and raycasting (see kintinuous_fast.ops.volume)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from kintinuous_fast.ops.volume import TSDF_SCALE
from kintinuous_ref.camera import Intrinsics
from kintinuous_ref.config import VolumeConfig
from kintinuous_ref.errors import ConfigError, DatasetError
from kintinuous_ref.tsdf import TsdfVolume, available_memory_bytes, volume_origin

BYTES_TSDF = 4  # int16 TSDF + int16 weight
BYTES_COLOUR = 4  # uint8 R, G, B + uint8 colour weight


@dataclass
class FastTsdfVolume:
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

    @property
    def resolution(self) -> int:
        return self.tsdf_weight.shape[0]

    @property
    def shifted(self) -> bool:
        return bool(np.any(self.offset))

    def offsets(self) -> tuple[int, int, int]:
        """The offset as three Python ints (o0, o1, o2), as the kernels take it."""
        o = np.asarray(self.offset, dtype=np.int64) % self.resolution
        return int(o[0]), int(o[1]), int(o[2])

    @property
    def size(self) -> float:
        return self.resolution * self.voxel_size

    def world_to_voxel(self, points: np.ndarray) -> np.ndarray:
        return (points - self.origin) / self.voxel_size

    def voxel_to_world(self, coordinates: np.ndarray) -> np.ndarray:
        return self.origin + coordinates * self.voxel_size


def memory_bytes(config: VolumeConfig) -> int:
    """Memory of a fast volume: 4 bytes per voxel, 8 with colour (1 GiB at 512^3)."""
    return (BYTES_TSDF + (BYTES_COLOUR if config.colour else 0)) * config.resolution**3


def check_volume_config(config: VolumeConfig, available: int | None = None) -> None:
    """The reference's checks with the fast volume's size against `available` bytes (host
    memory by default; the cuda backend passes the GPU's free memory)."""
    config.validate()
    if config.placement not in ("ahead", "centred"):
        raise ConfigError(
            f"volume placement must be 'ahead' or 'centred', got {config.placement!r}"
        )
    needed = memory_bytes(config)
    available = available_memory_bytes() if available is None else available
    if needed + (256 << 20) > available:
        raise ConfigError(
            f"a {config.resolution}^3 volume needs {needed / 2**30:.1f} GiB but only "
            f"{available / 2**30:.1f} GiB of memory is available; lower --resolution"
        )


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
    packed = volume.tsdf_weight
    packed = packed.copy_to_host() if hasattr(packed, "copy_to_host") else np.asarray(packed)
    colour = volume.colour
    if colour is not None and hasattr(colour, "copy_to_host"):
        colour = colour.copy_to_host()
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


def check_depth(depth: Any, camera: Intrinsics) -> None:
    if tuple(depth.shape) != (camera.height, camera.width):
        raise DatasetError(
            f"depth image is {tuple(depth.shape)}, camera expects {(camera.height, camera.width)}"
        )


def camera_frame_steps(volume: FastTsdfVolume, pose: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(base, steps) float32 with p_c(i, j, k) = base + i steps[0] + j steps[1] + k steps[2]:
    the camera-frame position of voxel (i, j, k), computed as the reference does."""
    rotation_t = pose[:3, :3].T
    base = (rotation_t @ (volume.origin - pose[:3, 3])).astype(np.float32)
    steps = np.ascontiguousarray((volume.voxel_size * rotation_t).T.astype(np.float32))
    return base, steps


def projection_constants(camera: Intrinsics) -> np.ndarray:
    """fx, fy, cx, cy as float32: NumPy 2 evaluates the reference's fx * x / z + cx in float32."""
    return np.array([camera.fx, camera.fy, camera.cx, camera.cy], dtype=np.float32)


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
    w, h = camera.width - 0.5, camera.height - 0.5
    corners = np.array([[-0.5, -0.5], [w, -0.5], [-0.5, h], [w, h]])
    rays = np.column_stack(
        [
            (corners[:, 0] - camera.cx) / camera.fx,
            (corners[:, 1] - camera.cy) / camera.fy,
            np.ones(4),
        ]
    )
    points = np.vstack([np.zeros(3), far * rays])
    coords = volume.world_to_voxel(points @ pose[:3, :3].T + pose[:3, 3])
    n = volume.resolution
    lo = np.clip(np.floor(coords.min(axis=0)).astype(np.int64) - 1, 0, n)
    hi = np.clip(np.ceil(coords.max(axis=0)).astype(np.int64) + 2, 0, n)
    if np.any(hi <= lo):
        return None
    return lo, hi


# ----------------------------------------------------------------------------------------------
# Per-frame set-up of raycasting


def empty_space_distance(negative_bricks: np.ndarray) -> np.ndarray:
    """kintinuous_ref.raycast._empty_space from its (B, B, B) map of bricks holding an observed
    negative voxel: grow by one brick, then the chessboard distance (in bricks) to the nearest
    grown brick (2 B everywhere when there is none), int64."""
    from scipy import ndimage

    bricks = ndimage.binary_dilation(negative_bricks, structure=np.ones((3, 3, 3), dtype=bool))
    if not bricks.any():
        return np.full(bricks.shape, 2 * len(bricks), dtype=np.int64)
    return ndimage.distance_transform_cdt(~bricks, metric="chessboard").astype(np.int64)
