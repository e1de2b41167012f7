"""Colour fusion helpers (paper VI): per-pixel colour weights and the colour of a surface point.

Artifact reduction (paper VI-B) decides how much each pixel's colour counts:
- near a depth discontinuity (the 7x7 check of preprocess.discontinuity_mask) it does not count at
  all, because misregistration between the depth and colour cameras and diffraction at object
  edges paint the background with the foreground's colour ("bloom", "colour bleed");
- otherwise it counts with the cosine of the angle between the viewing ray and the surface,
  cos(theta) = [0 0 1] . n = n_z (eq. 15), so colours seen straight on outweigh grazing views.
  The authors' code uses w_c = 2 min(1, |n_z| / 0.75), which saturates for views within ~41 deg
  of straight on; we follow the paper's plain cosine.
Both can be switched off (ColourConfig) to show their effect (the paper's Fig. 3).
"""

from __future__ import annotations

import numpy as np

from kintinuous_ref.config import ColourConfig
from kintinuous_ref.preprocess import PreprocessedFrame
from kintinuous_ref.tsdf import TsdfVolume


def angle_weight(normals: np.ndarray) -> np.ndarray:
    """|cos(theta)| = |n_z| of camera-frame unit normals (H, W, 3) (eq. 15); 0 where NaN.

    The absolute value makes the weight independent of which side the normals point to
    (ours point towards the camera, n_z < 0).
    """
    weight = np.abs(normals[..., 2])
    return np.where(np.isfinite(weight), weight, 0.0).astype(np.float32)


def colour_weights(frame: PreprocessedFrame, config: ColourConfig) -> np.ndarray:
    """Weight (H, W) float32 of each pixel's colour update; 0 = do not update (paper VI-B)."""
    weights = (frame.depth > 0).astype(np.float32)
    if config.discontinuity_check:
        weights *= frame.colour_mask
    if config.angle_weighting:
        weights *= angle_weight(frame.levels[0].normals)
    return weights


def surface_colour(volume: TsdfVolume, points: np.ndarray) -> np.ndarray:
    """RGB (M, 3) uint8 at world points (M, 3) by trilinear interpolation of the colour volume
    (paper VI-A), using only voxels that received colour; black where none around or no volume.
    """
    out = np.zeros((len(points), 3), dtype=np.uint8)
    if volume.colour is None or len(points) == 0:
        return out
    coords = volume.world_to_voxel(points)
    inside = np.all((coords >= 0) & (coords <= volume.resolution - 1), axis=-1)
    coords = coords[inside]
    # Weighting each corner by "has colour" and renormalising keeps never-coloured voxels
    # (value 0 = black) from darkening the surface.
    base = np.clip(np.floor(coords).astype(np.int64), 0, volume.resolution - 2)
    frac = coords - base
    total = np.zeros((len(coords), 3))
    coverage = np.zeros(len(coords))
    for corner in np.ndindex(2, 2, 2):
        offset = np.array(corner)
        # array cell of the logical voxel (cyclical buffer, tsdf.py; offset 0 if never shifted)
        i, j, k = ((base + offset + volume.offset) % volume.resolution).T
        w = np.prod(np.where(offset == 1, frac, 1.0 - frac), axis=-1)
        w = w * (volume.colour_weight[i, j, k] > 0)
        total += w[:, None] * volume.colour[i, j, k]
        coverage += w
    with np.errstate(invalid="ignore", divide="ignore"):
        rgb = total / coverage[:, None]
    rgb = np.where(coverage[:, None] > 1e-6, rgb, 0.0)
    out[inside] = np.clip(np.rint(rgb), 0, 255).astype(np.uint8)
    return out
