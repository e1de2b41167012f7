"""The TSDF volume and its colour volume, and KinectFusion's projective integration (paper III).

The volume is an axis-aligned cube of N^3 voxels in the WORLD frame (the dataset's frame, so poses
stay comparable with ground truth). Voxel (i, j, k) has its centre at origin + voxel_size (i, j, k).

Placement (a choice the papers leave to the implementation, config `volume.placement`):
- "ahead" (default): the volume's centre lies size/2 in front of the first camera along its optical
  axis. A camera looking along a world axis then sits at the centre of one face, looking in, so
  the whole volume covers what the first frame sees (KinectFusion's choice).
- "centred": the first camera sits at the volume's centre (Kintinuous, whose moving volume
  re-centres on the camera; without the moving volume half of the cube lies behind the camera).

Stored values (the reference keeps float32 everywhere for readability):
- tsdf in [-1, 1]: the signed distance along the ray divided by the truncation distance, positive
  in front of the surface (free space), negative behind; unobserved voxels hold 0 with weight 0.
- weight: number of observations, capped at `max_weight` (a running average that keeps adapting).
- colour (RGB 0..255) and colour_weight: the colour volume of paper VI, same grid.

Cyclical buffer (Kintinuous, paper III; kintinuous_ref.moving_volume): the arrays are a ring
buffer. Logical voxel (i, j, k), centred at origin + voxel_size (i, j, k), is stored at array cell
((i, j, k) + offset) mod N. Shifting the volume by whole voxels changes `origin` and `offset` and
moves no data; every function here and in raycast/colour/mesh indexes through `offset`, which is
zero for a volume that never moved (then array cell = logical voxel, as before).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from kintinuous_ref import memory
from kintinuous_ref.camera import Intrinsics
from kintinuous_ref.config import VolumeConfig
from kintinuous_ref.errors import ConfigError, DatasetError

# Bytes per voxel: tsdf + weight (float32) and colour RGB + weight (float32).
_BYTES_TSDF = 8
_BYTES_COLOUR = 16
# Voxels processed at once during integration (bounds the temporaries to a few hundred MB).
_SLAB_VOXELS = 1 << 20


class VoxelGrid:
    """Where a volume's voxels lie, for every volume type (TsdfVolume here, the fast backends'
    FastTsdfVolume): what reads only its `resolution`, `origin` (the world position of voxel
    (0, 0, 0)'s centre), `voxel_size` and `offset` (the cyclical buffer's)."""

    @property
    def shifted(self) -> bool:
        return bool(np.any(self.offset))

    @property
    def size(self) -> float:
        return self.resolution * self.voxel_size

    def world_to_voxel(self, points: np.ndarray) -> np.ndarray:
        """Continuous voxel coordinates (..., 3) of world points (..., 3)."""
        return (points - self.origin) / self.voxel_size

    def voxel_to_world(self, coordinates: np.ndarray) -> np.ndarray:
        return self.origin + coordinates * self.voxel_size


@dataclass
class TsdfVolume(VoxelGrid):
    tsdf: np.ndarray  # (N, N, N) float32, indexed [x, y, z]
    weight: np.ndarray  # (N, N, N) float32
    colour: np.ndarray | None  # (N, N, N, 3) float32 RGB 0..255, or None without colour
    colour_weight: np.ndarray | None  # (N, N, N) float32
    origin: np.ndarray  # (3,) world position of voxel (0, 0, 0)'s centre
    voxel_size: float
    truncation: float
    max_weight: float
    colour_max_weight: float = 255.0
    # (3,) int: array cell of logical voxel (0, 0, 0) (module docstring); zero until a shift
    offset: np.ndarray = field(default_factory=lambda: np.zeros(3, dtype=np.int64))

    @property
    def resolution(self) -> int:
        return self.tsdf.shape[0]

    def logical(self, array: np.ndarray) -> np.ndarray:
        """One of the volume's arrays in logical order (index = logical voxel): the array itself
        when the volume never shifted, else a re-ordered copy (for whole-volume passes such as
        meshing or the raycast's empty-space map, never for updates)."""
        if not self.shifted:
            return array
        return np.roll(array, tuple(-self.offset), axis=(0, 1, 2))

    def cells(self, start: tuple[int, int, int], stop: tuple[int, int, int]) -> tuple:
        """Index of the array cells holding the logical box [start, stop) (per axis, within
        0..N): plain slices (a view) when the box does not wrap, else np.ix_ index arrays
        (indexing then copies, so updates must be written back through the same index)."""
        n = self.resolution
        if not self.shifted:
            return tuple(slice(a, b) for a, b in zip(start, stop, strict=True))
        return np.ix_(
            *((np.arange(a, b) + o) % n for a, b, o in zip(start, stop, self.offset, strict=True))
        )


# ----------------------------------------------------------------------------------------------
# Creation


def memory_bytes(config: VolumeConfig) -> int:
    """Memory the reference volume needs (TSDF + weight, plus the colour volume if enabled)."""
    per_voxel = _BYTES_TSDF + (_BYTES_COLOUR if config.colour else 0)
    return per_voxel * config.resolution**3


def available_memory_bytes() -> int:
    """Memory this process can still allocate: the least of free memory, what `ulimit -v`
    leaves and what its cgroup leaves (kintinuous_ref.memory); MemAvailable alone would pass
    volumes that a limit then kills half way through a run."""
    return memory.available_bytes()


def refuse_if_too_big(
    config: VolumeConfig, needed: int, available: int, headroom: int, limited_by: str = ""
) -> None:
    """Refuse, in one line, a volume of `needed` bytes that leaves less than `headroom` of the
    `available` memory; each backend passes its own volume size and the memory it allocates
    from (host memory, or the GPU's). `limited_by` names the limit that set `available`."""
    if needed + headroom > available:
        where = f" (within {limited_by})" if limited_by else ""
        raise ConfigError(
            f"a {config.resolution}^3 volume needs {needed / 2**30:.1f} GiB but only "
            f"{available / 2**30:.1f} GiB of memory is available{where}; lower --resolution"
        )


def check_depth(depth: Any, camera: Intrinsics) -> None:
    """A one-line DatasetError for a depth image that does not fit the camera (host or device
    array: only its shape is read)."""
    if tuple(depth.shape) != (camera.height, camera.width):
        raise DatasetError(
            f"depth image is {tuple(depth.shape)}, camera expects {(camera.height, camera.width)}"
        )


def check_volume_config(config: VolumeConfig) -> None:
    """Refuse, in one line and before any work, a reference volume that cannot fit in host
    memory. The config's own fields were checked when it was made (VolumeConfig.__post_init__);
    a fast backend checks its volume with its own `check_volume_config`."""
    # Integration temporaries and the rest of the pipeline need headroom beside the volume.
    available = available_memory_bytes()
    tightest = memory.tightest()
    limited_by = tightest.source if tightest.bytes == available else ""
    refuse_if_too_big(config, memory_bytes(config), available, 1 << 30, limited_by)


def volume_origin(first_pose: np.ndarray, config: VolumeConfig) -> np.ndarray:
    """World position of voxel (0, 0, 0)'s centre for the placement rule (module docstring)."""
    camera_centre, optical_axis = first_pose[:3, 3], first_pose[:3, 2]
    if config.placement == "ahead":
        centre = camera_centre + 0.5 * config.size * optical_axis
    else:
        centre = camera_centre
    half_span = 0.5 * (config.resolution - 1) * config.voxel_size
    return centre - half_span


def make_volume(
    config: VolumeConfig, first_pose: np.ndarray, colour_max_weight: float = 255.0
) -> TsdfVolume:
    """An empty volume placed for the first camera pose (all weights 0). Memory taken by others
    between the check and the allocation is refused in the check's one line, not a bug's."""
    check_volume_config(config)
    n = config.resolution
    try:
        tsdf, weight = np.zeros((n, n, n), np.float32), np.zeros((n, n, n), np.float32)
        colour = np.zeros((n, n, n, 3), np.float32) if config.colour else None
        colour_weight = np.zeros((n, n, n), np.float32) if config.colour else None
    except MemoryError:
        raise ConfigError(
            f"a {n}^3 volume needs {memory_bytes(config) / 2**30:.1f} GiB: out of memory while "
            "allocating it; lower --resolution"
        ) from None
    return TsdfVolume(
        tsdf=tsdf,
        weight=weight,
        colour=colour,
        colour_weight=colour_weight,
        origin=volume_origin(np.asarray(first_pose, dtype=np.float64), config),
        voxel_size=config.voxel_size,
        truncation=config.truncation,
        max_weight=config.max_weight,
        colour_max_weight=colour_max_weight,
    )


# ----------------------------------------------------------------------------------------------
# Sampling


def corner_weights(
    shape: tuple[int, ...], coordinates: np.ndarray, offset: np.ndarray | None = None
) -> list[tuple[np.ndarray, np.ndarray]]:
    """(flat array index, trilinear weight) of the 8 voxels around each continuous LOGICAL
    coordinate (M, 3); `offset` is the cyclical buffer's (TsdfVolume.offset; None = zero).

    The weight of corner (a, b, c) is the product of f or 1 - f per axis, f the fractional part.
    Coordinates outside [0, N-1] are clamped onto the border cell.
    """
    n = np.array(shape[:3])
    base = np.clip(np.floor(coordinates).astype(np.int64), 0, n - 2)
    frac = np.clip(coordinates - base, 0.0, 1.0)
    wraps = offset is not None and bool(np.any(offset))
    if not wraps:
        flat = (base[:, 0] * n[1] + base[:, 1]) * n[2] + base[:, 2]
    corners = []
    for a, b, c in np.ndindex(2, 2, 2):
        w = (
            (frac[:, 0] if a else 1.0 - frac[:, 0])
            * (frac[:, 1] if b else 1.0 - frac[:, 1])
            * (frac[:, 2] if c else 1.0 - frac[:, 2])
        )
        if wraps:  # logical voxel base + (a, b, c) lives in array cell (. + offset) mod N
            cell = (base + (a, b, c) + offset) % n
            corners.append(((cell[:, 0] * n[1] + cell[:, 1]) * n[2] + cell[:, 2], w))
        else:
            corners.append((flat + (a * n[1] + b) * n[2] + c, w))
    return corners


def trilinear(
    grid: np.ndarray, coordinates: np.ndarray, offset: np.ndarray | None = None
) -> np.ndarray:
    """Trilinear interpolation of a (N, N, N[, C]) grid at continuous voxel coordinates (M, 3)
    (logical coordinates of a cyclical buffer with `offset`, see corner_weights)."""
    flat_grid = grid.reshape(-1, *grid.shape[3:])
    result = np.zeros((len(coordinates), *grid.shape[3:]))
    for index, w in corner_weights(grid.shape, coordinates, offset):
        result += (w[:, None] if grid.ndim == 4 else w) * flat_grid[index]
    return result.astype(np.float32)


def sample_tsdf(volume: TsdfVolume, coordinates: np.ndarray) -> np.ndarray:
    """Trilinear TSDF at continuous voxel coordinates (M, 3) over the OBSERVED voxels only.

    Never-observed voxels (weight 0) hold no distance, so they are left out and the weights of
    the others renormalised; NaN where none of the 8 is observed or the point is outside the grid.
    Leaving them out matters at the back of the truncation band, where a sample half a voxel
    from the last observed voxel would otherwise be pulled towards 0 (and the surface moved).
    """
    n = volume.resolution
    inside = np.all((coordinates >= 0) & (coordinates <= n - 1), axis=-1)
    tsdf, weight = volume.tsdf.reshape(-1), volume.weight.reshape(-1)
    total = np.zeros(len(coordinates))
    coverage = np.zeros(len(coordinates))
    for index, w in corner_weights(volume.tsdf.shape, coordinates, volume.offset):
        w = w * (weight[index] > 0)
        total += w * tsdf[index]
        coverage += w
    with np.errstate(invalid="ignore", divide="ignore"):
        value = total / coverage
    return np.where(inside & (coverage > 1e-6), value, np.nan)


# ----------------------------------------------------------------------------------------------
# Integration


def _frustum_corners(
    volume: TsdfVolume, depth: np.ndarray, pose: np.ndarray, camera: Intrinsics
) -> np.ndarray | None:
    """Voxel coordinates (5, 3) of the pyramid that holds every voxel this frame can update:
    the camera centre and the four image corners at the largest depth + truncation. None when
    the frame has no depth at all."""
    valid = depth[depth > 0]
    if valid.size == 0:
        return None
    far = float(valid.max()) + volume.truncation
    # Voxels round to a pixel, so the image spans [-0.5, size - 0.5) in projected coordinates.
    w, h = camera.width - 0.5, camera.height - 0.5
    corners = np.array([[-0.5, -0.5], [w, -0.5], [-0.5, h], [w, h]], dtype=np.float64)
    rays = np.column_stack(
        [(corners[:, 0] - camera.cx) / camera.fx, (corners[:, 1] - camera.cy) / camera.fy, [1] * 4]
    )
    # sdf >= -mu means |p_c| <= lambda D + mu, hence z = |p_c| / lambda <= D + mu <= far.
    points = np.vstack([np.zeros(3), far * rays])
    return volume.world_to_voxel(points @ pose[:3, :3].T + pose[:3, 3])


# The pyramid's edges: apex to each far corner, and the far rectangle.
_PYRAMID_EDGES = [(0, 1), (0, 2), (0, 3), (0, 4), (1, 2), (2, 4), (4, 3), (3, 1)]


def _slab_bounds(
    pyramid: np.ndarray, first: int, last: int, resolution: int
) -> tuple[int, int, int, int] | None:
    """Index ranges [j0, j1) x [k0, k1) of the pyramid's part with first <= x <= last.

    The part of a convex body inside a slab has as extreme points the body's vertices inside the
    slab and the crossings of its edges with the slab's two planes; their bounding box is exact.
    """
    points = [p for p in pyramid if first <= p[0] <= last]
    for a, b in _PYRAMID_EDGES:
        pa, pb = pyramid[a], pyramid[b]
        for plane in (first, last):
            if (pa[0] - plane) * (pb[0] - plane) < 0:
                points.append(pa + (plane - pa[0]) / (pb[0] - pa[0]) * (pb - pa))
    if not points:
        return None
    points = np.array(points)
    lo = np.clip(np.floor(points[:, 1:].min(axis=0)).astype(int), 0, resolution)
    hi = np.clip(np.ceil(points[:, 1:].max(axis=0)).astype(int) + 1, 0, resolution)
    if np.any(hi <= lo):
        return None
    return lo[0], hi[0], lo[1], hi[1]


def integrate(
    volume: TsdfVolume,
    depth: np.ndarray,
    pose: np.ndarray,
    camera: Intrinsics,
    colour: np.ndarray | None = None,
    colour_weights: np.ndarray | None = None,
) -> None:
    """Fuse one depth map (and optionally its colour) into the volume, in place (paper III).

    For every voxel centre p (world) with camera-frame position p_c = R^T (p - t):
      pixel x = round(pi(p_c)); lambda = ||K^-1 [x, 1]|| (the ray length per unit depth);
      sdf = lambda D(x) - ||p_c||           (signed distance along the ray, metres)
      if D(x) > 0 and sdf >= -truncation:   (behind the surface by more than mu: occluded, skip)
        F <- (W F + min(1, sdf / mu)) / (W + 1),  W <- min(W + 1, max_weight)
    Colour (paper VI-A): voxels with |sdf| < mu whose pixel has colour weight w_c > 0 get
      C <- (W_c C + w_c rgb) / (W_c + w_c),  W_c <- min(W_c + w_c, colour_max_weight)
    `colour_weights` (H, W) comes from colour.colour_weights (angle of observation and the
    depth-discontinuity check); None means weight 1 wherever there is depth.

    Only voxels inside the camera's viewing pyramid are visited, slab by slab along x (which
    also bounds the temporaries' memory at 512^3).
    """
    check_depth(depth, camera)
    pyramid = _frustum_corners(volume, depth, pose, camera)
    if pyramid is None:
        return
    n = volume.resolution
    i_lo = int(np.clip(np.floor(pyramid[:, 0].min()), 0, n))
    i_hi = int(np.clip(np.ceil(pyramid[:, 0].max()) + 1, 0, n))
    fuse_colour = colour is not None and volume.colour is not None
    if fuse_colour and colour_weights is None:
        colour_weights = (depth > 0).astype(np.float32)
    # lambda D per pixel, computed once per frame (the measured distance along each pixel's ray).
    rays = camera.ray_directions()
    ray_distance = (depth * np.linalg.norm(rays, axis=-1)).astype(np.float32).reshape(-1)

    # p_c = R^T (origin + s (i, j, k) - t) = base + i a_x + j a_y + k a_z: a sum of three
    # broadcast terms, so no grid of world coordinates is ever built.
    rotation_t = pose[:3, :3].T
    base = (rotation_t @ (volume.origin - pose[:3, 3])).astype(np.float32)
    axis_steps = (volume.voxel_size * rotation_t).T.astype(np.float32)  # rows: a_x, a_y, a_z
    slab = max(1, _SLAB_VOXELS // (n * n))
    for i0 in range(i_lo, i_hi, slab):
        i1 = min(i0 + slab, i_hi)
        bounds = _slab_bounds(pyramid, i0, i1 - 1, n)
        if bounds is None:
            continue
        j0, j1, k0, k1 = bounds
        i = np.arange(i0, i1, dtype=np.float32)[:, None, None, None]
        j = np.arange(j0, j1, dtype=np.float32)[None, :, None, None]
        k = np.arange(k0, k1, dtype=np.float32)[None, None, :, None]
        cam = base + i * axis_steps[0] + j * axis_steps[1] + k * axis_steps[2]
        x, y, z = cam[..., 0], cam[..., 1], cam[..., 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            u = np.rint(camera.fx * x / z + camera.cx)
            v = np.rint(camera.fy * y / z + camera.cy)
        in_image = (z > 0) & (u >= 0) & (u < camera.width) & (v >= 0) & (v < camera.height)
        pixel = np.where(in_image, v * camera.width + u, 0).astype(np.int64)
        measured = np.where(in_image, ray_distance[pixel], 0.0)
        sdf = measured - np.sqrt(x * x + y * y + z * z)
        update = (measured > 0) & (sdf >= -volume.truncation)

        # The array cells of this logical block: views, or copies in a shifted cyclical buffer
        # (written back below).
        block = volume.cells((i0, j0, k0), (i1, j1, k1))
        tsdf, weight = volume.tsdf[block], volume.weight[block]
        observed = np.minimum(1.0, sdf[update] / volume.truncation)
        w_old = weight[update]
        tsdf[update] = (tsdf[update] * w_old + observed) / (w_old + 1.0)
        weight[update] = np.minimum(w_old + 1.0, volume.max_weight)
        if volume.shifted:
            volume.tsdf[block], volume.weight[block] = tsdf, weight

        if fuse_colour:
            w_pixel = colour_weights.reshape(-1)[pixel]
            near = update & (np.abs(sdf) < volume.truncation) & (w_pixel > 0)
            rgb = colour.reshape(-1, 3)[pixel[near]].astype(np.float32)
            w_c = w_pixel[near][:, None]
            c_block, cw_block = volume.colour[block], volume.colour_weight[block]
            cw_old = cw_block[near][:, None]
            c_block[near] = (c_block[near] * cw_old + rgb * w_c) / (cw_old + w_c)
            cw_block[near] = np.minimum(cw_old + w_c, volume.colour_max_weight)[:, 0]
            if volume.shifted:
                volume.colour[block], volume.colour_weight[block] = c_block, cw_block
