"""Model prediction: vertex, normal and colour maps of the fused surface seen from a pose
(KinectFusion's surface prediction; paper III and VI-A). ICP tracks the next frame against this.

For each pixel a ray leaves the camera centre through the pixel centre. It starts where it enters
the volume and marches in steps of 0.8 x truncation (docs/parameters.md: behind a surface only a
band about one truncation deep is ever observed, so a step shorter than that always puts a
sample inside the band, where a longer one can leap from free space into unobserved space and
miss the crossing) sampling the TSDF trilinearly. The first change of sign from + to - is the
surface; its position is refined by linear interpolation of the two samples around it,

    t* = t - step F(t) / (F(t) - F(t - step)),

the normal is the normalised TSDF gradient (central differences, one voxel apart), pointing from
the surface towards free space (towards the camera), and the colour is the colour volume's
trilinear interpolation at the crossing. A change from - to + means the ray entered the model from
behind (a back face): the ray stops with no surface. Samples whose 8 surrounding voxels are not all
observed are "unknown" and never form a crossing.

All rays march together; rays that finish leave the working set, so the cost follows the rays
still searching.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from kintinuous_ref.camera import Intrinsics
from kintinuous_ref.colour import surface_colour
from kintinuous_ref.tsdf import TsdfVolume, sample_tsdf, trilinear

STEP_FRACTION = 0.8  # of the truncation distance (docs/parameters.md)
BRICK = 8  # voxels per side of the blocks that empty-space skipping steps over


def check_stride(stride: int) -> None:
    """The pixel stride of a raycast: a whole number >= 1."""
    if not isinstance(stride, (int, np.integer)) or isinstance(stride, bool) or stride < 1:
        raise ValueError(f"raycast stride must be a whole number >= 1, got {stride!r}")


@dataclass
class ModelPrediction:
    pose: np.ndarray  # camera-to-world pose it was rendered from
    vertices: np.ndarray  # (H, W, 3) float32 WORLD frame, NaN = no surface
    normals: np.ndarray  # (H, W, 3) float32 WORLD frame unit, NaN = no surface
    colours: np.ndarray  # (H, W, 3) uint8 RGB (zeros where no surface or no colour volume)


def _volume_entry_exit(
    volume: TsdfVolume, origin: np.ndarray, directions: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Ray parameters where each ray enters and leaves the box of voxel centres (slab method)."""
    lower = volume.origin
    upper = volume.origin + (volume.resolution - 1) * volume.voxel_size
    with np.errstate(divide="ignore", invalid="ignore"):
        t_lower = (lower - origin) / directions
        t_upper = (upper - origin) / directions
    # A ray parallel to an axis inside the slab: that axis does not limit it.
    parallel = directions == 0
    inside = (origin >= lower) & (origin <= upper)
    t_lower = np.where(parallel, np.where(inside, -np.inf, np.inf), t_lower)
    t_upper = np.where(parallel, np.where(inside, np.inf, -np.inf), t_upper)
    entry = np.minimum(t_lower, t_upper).max(axis=-1)
    exit_ = np.maximum(t_lower, t_upper).min(axis=-1)
    return np.maximum(entry, 0.0), exit_


def _gradient_normals(volume: TsdfVolume, points: np.ndarray) -> np.ndarray:
    """Unit TSDF gradient at world points (M, 3) by central differences; NaN if degenerate."""
    coords = volume.world_to_voxel(points)
    limit = volume.resolution - 1
    gradient = np.zeros_like(coords)
    for axis in range(3):
        offset = np.zeros(3)
        offset[axis] = 1.0
        ahead = trilinear(volume.tsdf, np.clip(coords + offset, 0, limit), volume.offset)
        behind = trilinear(volume.tsdf, np.clip(coords - offset, 0, limit), volume.offset)
        gradient[:, axis] = ahead - behind
    length = np.linalg.norm(gradient, axis=-1, keepdims=True)
    with np.errstate(invalid="ignore", divide="ignore"):
        normals = gradient / length
    normals[~(length[:, 0] > 0)] = np.nan
    return normals


def _interpolate(t0: np.ndarray, f0: np.ndarray, t1: np.ndarray, f1: np.ndarray) -> np.ndarray:
    """Where the line through (t0, f0) and (t1, f1) crosses zero (f0 > 0 > f1)."""
    return t0 + (t1 - t0) * f0 / (f0 - f1)


def _refine_crossing(
    volume: TsdfVolume,
    origin: np.ndarray,
    directions: np.ndarray,
    t0: np.ndarray,
    f0: np.ndarray,
    t1: np.ndarray,
    f1: np.ndarray,
) -> np.ndarray:
    """Zero crossing between samples t0 (F > 0) and t1 (F < 0): linear interpolation, then one
    regula falsi step with a sample at the estimate, which lies inside the band where every
    voxel is observed and the TSDF is a linear function of distance, so the step removes what
    the far sample's missing neighbours did to the first estimate."""
    estimate = _interpolate(t0, f0, t1, f1)
    f = sample_tsdf(volume, volume.world_to_voxel(origin + estimate[:, None] * directions))
    ahead = f > 0  # the surface lies between the estimate and t1
    behind = f < 0
    refined = estimate.copy()
    refined[ahead] = _interpolate(estimate[ahead], f[ahead], t1[ahead], f1[ahead])
    refined[behind] = _interpolate(t0[behind], f0[behind], estimate[behind], f[behind])
    return refined


def empty_space(volume: TsdfVolume) -> np.ndarray:
    """Per brick of BRICK^3 voxels, the chessboard distance (in bricks) to the nearest brick
    that holds, or borders, an observed voxel with negative TSDF; 0 for those bricks.

    A trilinear sample only reads the 8 voxels around it and the renormalised mean of
    non-negative values is non-negative, so a sample in a brick at distance D >= 1 cannot be < 0,
    and neither can any sample in the cube of bricks within D - 1 of it: no zero crossing and no
    back face can complete there. Growing the negative bricks by one brick covers samples whose
    8 voxels straddle a brick border.
    """
    n, b = volume.resolution, -(-volume.resolution // BRICK)
    negative = np.zeros((b * BRICK,) * 3, dtype=bool)
    # In logical order: bricks are blocks of logical voxels (cyclical buffer, tsdf.py).
    negative[:n, :n, :n] = volume.logical((volume.tsdf < 0) & (volume.weight > 0))
    bricks = negative.reshape(b, BRICK, b, BRICK, b, BRICK).any(axis=(1, 3, 5))
    bricks = ndimage.binary_dilation(bricks, structure=np.ones((3, 3, 3), dtype=bool))
    if not bricks.any():
        return np.full(bricks.shape, 2 * b, dtype=np.int64)  # nothing anywhere: skip it all
    return ndimage.distance_transform_cdt(~bricks, metric="chessboard").astype(np.int64)


def _march(
    volume: TsdfVolume,
    origin: np.ndarray,
    directions: np.ndarray,
    skip_empty: bool = True,
) -> np.ndarray:
    """Ray parameter (metres along unit `directions`) of each ray's first + to - zero crossing,
    NaN where there is none (see the module docstring).

    Samples lie on the grid t = entry + m step. With `skip_empty` a ray in empty space
    (empty_space) jumps to the first grid sample past the empty cube around it instead of
    sampling it; the samples that decide are the same, so the answer is exactly that of the plain
    march (the tests check this), only faster: most of a ray runs through free space.
    """
    entry, exit_ = _volume_entry_exit(volume, origin, directions)
    step = STEP_FRACTION * volume.truncation
    distance = empty_space(volume) if skip_empty else None
    hit_t = np.full(len(directions), np.nan)
    active = np.flatnonzero(entry < exit_)
    m = np.zeros(len(active), dtype=np.int64)  # sample number along the ray
    previous = np.full(len(active), np.nan)  # TSDF at sample m - 1 (NaN: none or unknown)
    previous_known = np.ones(len(active), dtype=bool)  # False right after a jump
    while len(active):
        t = entry[active] + m * step
        coords = volume.world_to_voxel(origin + t[:, None] * directions[active])
        if distance is None:
            near = np.ones(len(active), dtype=bool)
        else:
            brick = np.clip(np.floor(coords).astype(np.int64) // BRICK, 0, len(distance) - 1)
            empty_radius = distance[brick[:, 0], brick[:, 1], brick[:, 2]]
            near = empty_radius == 0
        m_next = m + 1
        finished = np.zeros(len(active), dtype=bool)

        # Rays in empty space: jump to the first grid sample beyond the empty cube of bricks
        # around them (bricks within distance - 1 of theirs).
        far = np.flatnonzero(~near)
        if len(far):
            velocity = directions[active[far]] / volume.voxel_size  # voxels per metre
            reach = empty_radius[far, None] - 1
            corner = np.where(velocity > 0, (brick[far] + reach + 1), (brick[far] - reach)) * BRICK
            with np.errstate(divide="ignore", invalid="ignore"):
                to_border = np.where(velocity != 0, (corner - coords[far]) / velocity, np.inf)
            t_border = t[far] + to_border.min(axis=1)
            m_border = np.floor((t_border - entry[active[far]]) / step).astype(np.int64) + 1
            m_next[far] = np.maximum(m[far] + 1, m_border)
            previous_known[far] = False

        # Rays near the surface: sample, recovering the previous sample after a jump.
        close = np.flatnonzero(near)
        if len(close):
            unknown = close[~previous_known[close]]
            if len(unknown):
                t_before = entry[active[unknown]] + (m[unknown] - 1) * step
                before = volume.world_to_voxel(
                    origin + t_before[:, None] * directions[active[unknown]]
                )
                previous[unknown] = np.where(m[unknown] > 0, sample_tsdf(volume, before), np.nan)
            value = sample_tsdf(volume, coords[close])
            f0 = previous[close]
            crossing = (f0 > 0) & (value < 0)
            back_face = (f0 < 0) & (value > 0)
            if np.any(crossing):
                rays = close[crossing]
                hit_t[active[rays]] = _refine_crossing(
                    volume,
                    origin,
                    directions[active[rays]],
                    t[rays] - step,
                    f0[crossing],
                    t[rays],
                    value[crossing],
                )
            finished[close] = crossing | back_face
            previous[close] = value
            previous_known[close] = True

        keep = ~finished & (entry[active] + m_next * step <= exit_[active])
        active, m = active[keep], m_next[keep]
        previous, previous_known = previous[keep], previous_known[keep]
    return hit_t


def raycast(
    volume: TsdfVolume,
    pose: np.ndarray,
    camera: Intrinsics,
    skip_empty: bool = True,
    colour: bool = True,
    stride: int = 1,
) -> ModelPrediction:
    """Vertex, normal and colour maps of the model surface seen from `pose` (world frame).
    `colour` False leaves the colour map black: the trackers read only vertices and normals
    (the RGB-D term compares the raw frames, paper IV), so the pipeline's prediction skips it.
    `stride` s > 1 casts only the rays of pixels (u, v) with u and v multiples of s, all that
    level log2(s) of preprocess.model_pyramid keeps (the fast-odometry setting's ICP starts
    there); the other pixels stay empty."""
    height, width = camera.height, camera.width
    check_stride(stride)
    rays = camera.ray_directions()[::stride, ::stride].reshape(-1, 3).astype(np.float64)
    directions = rays @ pose[:3, :3].T
    directions /= np.linalg.norm(directions, axis=-1, keepdims=True)
    origin = pose[:3, 3].astype(np.float64)
    hit_t = _march(volume, origin, directions, skip_empty)
    rows, columns = np.mgrid[0:height:stride, 0:width:stride]
    cast_pixels = (rows * width + columns).ravel()  # flat index of each ray's pixel

    found = np.flatnonzero(np.isfinite(hit_t))
    points = origin + hit_t[found, None] * directions[found]
    found = cast_pixels[found]
    vertices = np.full((height * width, 3), np.nan, dtype=np.float32)
    normals = np.full((height * width, 3), np.nan, dtype=np.float32)
    colours = np.zeros((height * width, 3), dtype=np.uint8)
    vertices[found] = points
    normals[found] = _gradient_normals(volume, points)
    if colour:
        colours[found] = surface_colour(volume, points)
    # A surface point without a usable normal is no use to ICP: drop it.
    no_normal = np.isnan(normals[:, 0])
    vertices[no_normal] = np.nan
    colours[no_normal] = 0
    return ModelPrediction(
        pose=np.array(pose, dtype=np.float64),
        vertices=vertices.reshape(height, width, 3),
        normals=normals.reshape(height, width, 3),
        colours=colours.reshape(height, width, 3),
    )


def predict_surface(
    volume: TsdfVolume, pose: np.ndarray, camera: Intrinsics, stride: int = 1
) -> ModelPrediction:
    """The model prediction the next frame tracks against (the pipeline's step 6): vertex and
    normal maps from `pose`, no colour (the trackers read none), every `stride`-th pixel."""
    return raycast(volume, pose, camera, colour=False, stride=stride)
