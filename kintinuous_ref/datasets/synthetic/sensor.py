"""A Kinect-like sensor: what turns exact ray-cast depth and colour into measurements.

Always applied (the sensor's working range, deterministic): depth only between `min_depth` and
`max_depth`. With noise (each part can be switched off):
- axial noise growing with depth, sigma(z) = 0.0012 + 0.0019 (z - 0.4)^2 m (Nguyen, Izadi and
  Lovell, 3DIMPVT 2012, for angles to the surface below about 60 degrees);
- no depth at grazing angles (angle between the ray and the normal above `grazing_angle_deg`),
  where the projected pattern is too stretched to be matched;
- dropouts along depth discontinuities (the pattern is occluded there): edge pixels, and each of
  their neighbours with probability `edge_dropout`;
- quantisation to the 1/depth_scale depth units of the stored PNG (1/5000 m);
- colour: Gaussian read noise plus shot noise (variance grows with the signal).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from kintinuous_ref import camera


@dataclass(frozen=True)
class SensorModel:
    min_depth: float = 0.4  # metres; the Kinect sees nothing closer
    max_depth: float = 4.0  # metres; farther surfaces give no depth
    axial_noise: bool = True
    grazing_angle_deg: float | None = 80.0  # None: keep every angle
    edge_jump: float = 0.06  # relative depth jump (|dz| / z) that counts as a discontinuity
    edge_dropout: float | None = 0.5  # None: no dropouts at discontinuities
    quantise: bool = True
    colour_read_noise: float | None = 1.5  # intensity levels (0..255); None: exact colour
    colour_shot_noise: float = 0.01  # variance per level of signal

    @classmethod
    def exact(cls) -> SensorModel:
        """The ideal sensor: exact depth within the working range, exact colour."""
        return cls(
            axial_noise=False,
            grazing_angle_deg=None,
            edge_dropout=None,
            quantise=False,
            colour_read_noise=None,
        )


def depth_edges(depth: np.ndarray, relative_jump: float) -> np.ndarray:
    """Pixels with a 4-neighbour whose depth differs by more than relative_jump * depth.

    `depth` may hold inf (no surface): a jump to nothing is a discontinuity too.
    """
    finite = np.where(np.isfinite(depth), depth, 1e6)
    edges = np.zeros(depth.shape, dtype=bool)
    for axis in (0, 1):
        a, b = (finite[1:], finite[:-1]) if axis == 0 else (finite[:, 1:], finite[:, :-1])
        jump = np.abs(a - b) > relative_jump * np.minimum(a, b)
        if axis == 0:
            edges[1:] |= jump
            edges[:-1] |= jump
        else:
            edges[:, 1:] |= jump
            edges[:, :-1] |= jump
    return edges


def measure_depth(
    depth: np.ndarray,
    cos_incidence: np.ndarray,
    model: SensorModel,
    depth_scale: float,
    rng: np.random.Generator,
    focal: float = 525.0,
) -> np.ndarray:
    """Sensor depth (H, W) float32 metres, 0 = no measurement, from exact depth (inf = no hit).

    `focal` (pixels): on a plane seen at angle a the depth changes by about tan(a) / focal
    (relative) per pixel, so small images need a larger jump before it counts as an edge.
    """
    valid = np.isfinite(depth) & (depth >= model.min_depth) & (depth <= model.max_depth)
    if model.grazing_angle_deg is not None:
        valid &= cos_incidence >= np.cos(np.radians(model.grazing_angle_deg))
    if model.edge_dropout is not None:
        max_slope = np.tan(np.radians(model.grazing_angle_deg or 80.0))
        edges = depth_edges(depth, max(model.edge_jump, max_slope / focal))
        grown = cv2.dilate(edges.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
        valid &= ~edges & ~(grown & (rng.random(depth.shape) < model.edge_dropout))
    measured = np.where(valid, depth, 0.0)
    if model.axial_noise:
        noise = rng.standard_normal(depth.shape) * camera.axial_noise(measured)
        measured = measured + valid * noise
    if model.quantise:
        measured = np.round(measured * depth_scale) / depth_scale
    measured = np.where(valid & (measured > 0), measured, 0.0)
    return measured.astype(np.float32)


def measure_colour(
    colour: np.ndarray, brightness: float, model: SensorModel, rng: np.random.Generator
) -> np.ndarray:
    """Sensor colour (H, W, 3) uint8 RGB from exact colour in [0, 1] under a light level."""
    signal = colour * np.float32(255.0 * brightness)
    if model.colour_read_noise is not None:
        variance = (
            np.float32(model.colour_read_noise**2) + np.float32(model.colour_shot_noise) * signal
        )
        signal += rng.standard_normal(signal.shape, dtype=np.float32) * np.sqrt(variance)
    return np.clip(np.round(signal), 0, 255).astype(np.uint8)
