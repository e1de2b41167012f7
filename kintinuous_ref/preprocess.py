"""Frame preprocessing (paper IV-A.1, KinectFusion's measurement stage).

For every incoming RGB-D pair this module produces what tracking and fusion need:

- metric depth (0 = no measurement) with far readings dropped,
- a bilateral-filtered copy of the depth for vertex/normal maps (KinectFusion: ICP is smoother on
  filtered depth, while the TSDF integrates the raw depth),
- the intensity image I = 0.299 R + 0.587 G + 0.114 B (paper IV-A.1),
- four-level pyramids built with a 5x5 Gaussian; for depth the Gaussian ignores neighbours that
  differ from the centre by more than 3 sigma_depth so that depth edges are not blurred,
- vertex and normal maps at every level (camera frame, NaN = invalid),
- intensity derivatives: 3x3 Sobel scaled by 1/8 after a 3x3 Gaussian (sigma 0.8),
- the 7x7 depth-discontinuity mask of paper VI-B, which decides where colour may be fused.

Pyramid convention (camera.py): pixel (u, v) of level l+1 sits on pixel (2u, 2v) of level l, so
each downsampled value is a Gaussian average *centred on the even pixel*.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from kintinuous_ref.camera import Intrinsics
from kintinuous_ref.config import PreprocessConfig
from kintinuous_ref.errors import DatasetError

# 5x5 binomial approximation of a Gaussian (the kernel of OpenCV's pyrDown): outer([1,4,6,4,1])/256.
_BINOMIAL_5 = np.array([1.0, 4.0, 6.0, 4.0, 1.0]) / 16.0
# Sobel kernels; with the 1/8 scale the response is the intensity change per pixel.
_SOBEL_X = np.array([[-1.0, 0.0, 1.0], [-2.0, 0.0, 2.0], [-1.0, 0.0, 1.0]]) / 8.0
_SOBEL_Y = _SOBEL_X.T


@dataclass
class PyramidLevel:
    """One pyramid level of a preprocessed frame (camera frame, metres, NaN = invalid)."""

    camera: Intrinsics
    depth: np.ndarray  # (h, w) float32 raw depth, edge-aware Gaussian pyramid, 0 = invalid
    vertices: np.ndarray  # (h, w, 3) float32 from the bilateral-filtered depth pyramid
    normals: np.ndarray  # (h, w, 3) float32 unit, pointing towards the camera
    intensity: np.ndarray  # (h, w) float32, 0..255
    intensity_dx: np.ndarray  # (h, w) float32, intensity units per pixel
    intensity_dy: np.ndarray  # (h, w) float32


@dataclass
class PreprocessedFrame:
    colour: np.ndarray  # (H, W, 3) uint8 RGB
    depth: np.ndarray  # (H, W) float32 metres, raw (what TSDF integration uses)
    levels: list[PyramidLevel]  # 0 = full resolution
    colour_mask: np.ndarray  # (H, W) bool: colour may be fused here (7x7 discontinuity check)


# ----------------------------------------------------------------------------------------------
# Small image helpers: all filters are written as sums of shifted copies, which is short,
# vectorised and makes the border rule (ignore what lies outside the image) explicit.


def _shifted(image: np.ndarray, dy: int, dx: int, fill: float) -> np.ndarray:
    """image[v + dy, u + dx] for every (v, u), `fill` where that falls outside the image."""
    height, width = image.shape[:2]
    out = np.full_like(image, fill)
    src_y = slice(max(0, dy), min(height, height + dy))
    src_x = slice(max(0, dx), min(width, width + dx))
    dst_y = slice(max(0, -dy), min(height, height - dy))
    dst_x = slice(max(0, -dx), min(width, width - dx))
    out[dst_y, dst_x] = image[src_y, src_x]
    return out


def _correlate3x3(image: np.ndarray, kernel: np.ndarray) -> np.ndarray:
    """3x3 correlation with replicated borders (so a constant image has zero derivative)."""
    padded = np.pad(image, 1, mode="edge")
    height, width = image.shape
    out = np.zeros_like(image)
    for dy in range(3):
        for dx in range(3):
            out += kernel[dy, dx] * padded[dy : dy + height, dx : dx + width]
    return out


def _gaussian3x3(sigma: float) -> np.ndarray:
    g = np.exp(-(np.array([-1.0, 0.0, 1.0]) ** 2) / (2.0 * sigma**2))
    g /= g.sum()
    return np.outer(g, g)


# ----------------------------------------------------------------------------------------------
# Depth


def metric_depth(depth: np.ndarray, max_depth: float, depth_scale: float = 5000.0) -> np.ndarray:
    """float32 metres with 0 wherever there is no trustworthy measurement (NaN, <= 0, too far).

    Integer images are raw sensor units (TUM: 5000 per metre) and are divided by `depth_scale`;
    floating-point images are taken to be metres already (the datasets' convention).
    """
    depth = np.asarray(depth)
    if np.issubdtype(depth.dtype, np.integer):
        depth = depth.astype(np.float32) / np.float32(depth_scale)
    depth = depth.astype(np.float32, copy=False)
    valid = np.isfinite(depth) & (depth > 0) & (depth <= max_depth)
    return np.where(valid, depth, np.float32(0.0))


def bilateral_filter(
    depth: np.ndarray, sigma_space: float, sigma_depth: float, radius: int
) -> np.ndarray:
    """Edge-preserving smoothing of a depth map (KinectFusion's first step).

    D'(p) = sum_q w_s(|p-q|) w_r(|D(p)-D(q)|) D(q) / sum_q w_s w_r over the (2r+1)^2 window, with
    Gaussian weights of widths sigma_space (pixels) and sigma_depth (metres). Pixels without depth
    neither contribute nor receive a value (a hole stays a hole).
    """
    total = np.zeros(depth.shape, dtype=np.float64)
    weights = np.zeros(depth.shape, dtype=np.float64)
    centre = depth.astype(np.float64)
    for dy in range(-radius, radius + 1):
        for dx in range(-radius, radius + 1):
            neighbour = _shifted(centre, dy, dx, 0.0)
            spatial = np.exp(-(dx * dx + dy * dy) / (2.0 * sigma_space**2))
            w = spatial * np.exp(-((centre - neighbour) ** 2) / (2.0 * sigma_depth**2))
            w *= neighbour > 0
            total += w * neighbour
            weights += w
    filtered = np.divide(total, weights, out=np.zeros_like(total), where=weights > 0)
    return np.where(depth > 0, filtered, 0.0).astype(np.float32)


def pyramid_down_depth(depth: np.ndarray, cutoff: float) -> np.ndarray:
    """Half-size depth: 5x5 Gaussian centred on each even pixel, ignoring invalid neighbours and
    neighbours more than `cutoff` from the centre (so foreground and background never mix)."""
    height, width = depth.shape[0] // 2, depth.shape[1] // 2
    centre = depth[0 : 2 * height : 2, 0 : 2 * width : 2].astype(np.float64)
    total = np.zeros_like(centre)
    weights = np.zeros_like(centre)
    for dy in range(-2, 3):
        for dx in range(-2, 3):
            shifted = _shifted(depth.astype(np.float64), dy, dx, 0.0)
            neighbour = shifted[0 : 2 * height : 2, 0 : 2 * width : 2]
            use = (neighbour > 0) & (np.abs(neighbour - centre) <= cutoff)
            w = _BINOMIAL_5[dy + 2] * _BINOMIAL_5[dx + 2] * use
            total += w * neighbour
            weights += w
    out = np.divide(total, weights, out=np.zeros_like(total), where=weights > 0)
    return np.where(centre > 0, out, 0.0).astype(np.float32)


def pyramid_down_intensity(image: np.ndarray) -> np.ndarray:
    """Half-size image by the 5x5 Gaussian centred on each even pixel (weights renormalised at
    the border instead of inventing pixels outside the image)."""
    height, width = image.shape[0] // 2, image.shape[1] // 2
    inside = np.ones(image.shape, dtype=np.float64)
    total = np.zeros((height, width))
    weights = np.zeros((height, width))
    for dy in range(-2, 3):
        for dx in range(-2, 3):
            w = _BINOMIAL_5[dy + 2] * _BINOMIAL_5[dx + 2]
            total += w * _shifted(image.astype(np.float64), dy, dx, 0.0)[::2, ::2][:height, :width]
            weights += w * _shifted(inside, dy, dx, 0.0)[::2, ::2][:height, :width]
    return (total / weights).astype(np.float32)


def vertex_map(depth: np.ndarray, camera: Intrinsics) -> np.ndarray:
    """Camera-frame points V(u, v) = D(u, v) K^-1 [u, v, 1]^T (paper IV-A.2); NaN where D = 0."""
    vertices = camera.backproject(depth.astype(np.float32))
    vertices[depth <= 0] = np.nan
    return vertices


def normal_map(vertices: np.ndarray) -> np.ndarray:
    """Unit normals from the cross product of neighbour differences (KinectFusion).

    n(u, v) = normalise((V(u, v+1) - V(u, v)) x (V(u+1, v) - V(u, v))). With x right, y down and
    z forward this order makes normals point towards the camera (n_z < 0 on a surface facing it),
    the same side as the TSDF gradient of the model. NaN where a neighbour is missing.
    """
    down = np.full_like(vertices, np.nan)
    right = np.full_like(vertices, np.nan)
    down[:-1] = vertices[1:] - vertices[:-1]
    right[:, :-1] = vertices[:, 1:] - vertices[:, :-1]
    normals = np.cross(down, right)
    length = np.linalg.norm(normals, axis=-1, keepdims=True)
    with np.errstate(invalid="ignore", divide="ignore"):
        normals = normals / length
    normals[~(length[..., 0] > 0)] = np.nan
    return normals.astype(np.float32)


# ----------------------------------------------------------------------------------------------
# Intensity


def intensity_image(colour: np.ndarray) -> np.ndarray:
    """I = 0.299 R + 0.587 G + 0.114 B (paper IV-A.1), float32 in 0..255."""
    rgb = colour.astype(np.float32)
    return 0.299 * rgb[..., 0] + 0.587 * rgb[..., 1] + 0.114 * rgb[..., 2]


def intensity_gradients(intensity: np.ndarray, blur_sigma: float) -> tuple[np.ndarray, np.ndarray]:
    """dI/du, dI/dv: 3x3 Gaussian blur (sigma 0.8, paper IV-A.1) then 3x3 Sobel scaled by 1/8."""
    blurred = _correlate3x3(intensity.astype(np.float64), _gaussian3x3(blur_sigma))
    dx = _correlate3x3(blurred, _SOBEL_X)
    dy = _correlate3x3(blurred, _SOBEL_Y)
    return dx.astype(np.float32), dy.astype(np.float32)


# ----------------------------------------------------------------------------------------------
# Colour reliability (paper VI-B)


def discontinuity_mask(depth: np.ndarray, window: int, jump: float, max_bad: int) -> np.ndarray:
    """True where colour may be fused: the pixel has depth and at most `max_bad` of its neighbours
    in the window x window neighbourhood differ from it by more than `jump` metres (paper VI-B).

    A neighbour without depth counts as bad (it usually borders a shadow or the sky of the scene,
    i.e. a depth edge); neighbours outside the image are not counted.
    """
    radius = window // 2
    bad = np.zeros(depth.shape, dtype=np.int32)
    for dy in range(-radius, radius + 1):
        for dx in range(-radius, radius + 1):
            if dy == 0 and dx == 0:
                continue
            neighbour = _shifted(depth, dy, dx, np.nan)  # NaN: outside, never "bad"
            bad += np.abs(neighbour - depth) > jump
    return (depth > 0) & (bad <= max_bad)


# ----------------------------------------------------------------------------------------------
# The whole stage


def check_frame_inputs(colour: Any, depth: Any, camera: Intrinsics) -> None:
    """A one-line DatasetError for images that do not fit the camera. Only shape and dtype are
    read, so host and device arrays (the fast backends') are checked alike."""
    expected = (camera.height, camera.width)
    depth_shape, colour_shape = tuple(depth.shape), tuple(colour.shape)
    if depth_shape != expected:
        raise DatasetError(f"depth image is {depth_shape}, expected {expected} from the camera")
    if colour_shape != (*expected, 3) or colour.dtype != np.uint8:
        raise DatasetError(
            f"colour image is {colour_shape} {colour.dtype}, expected {(*expected, 3)} uint8 RGB"
        )


def preprocess_frame(
    colour: np.ndarray, depth: np.ndarray, camera: Intrinsics, config: PreprocessConfig
) -> PreprocessedFrame:
    """Everything tracking and fusion need from one RGB-D pair (see the module docstring)."""
    check_frame_inputs(colour, depth, camera)
    raw = metric_depth(depth, config.max_depth, camera.depth_scale)
    filtered = bilateral_filter(
        raw, config.bilateral_sigma_space, config.bilateral_sigma_depth, config.bilateral_radius
    )
    intensity = intensity_image(colour)
    levels: list[PyramidLevel] = []
    for level in range(config.pyramid_levels):
        if level > 0:
            raw = pyramid_down_depth(raw, config.pyramid_depth_cutoff)
            filtered = pyramid_down_depth(filtered, config.pyramid_depth_cutoff)
            intensity = pyramid_down_intensity(intensity)
        level_camera = camera.at_level(level)
        vertices = vertex_map(filtered, level_camera)
        dx, dy = intensity_gradients(intensity, config.gradient_blur_sigma)
        levels.append(
            PyramidLevel(level_camera, raw, vertices, normal_map(vertices), intensity, dx, dy)
        )
    mask = discontinuity_mask(
        levels[0].depth,
        config.discontinuity_window,
        config.discontinuity_jump,
        config.discontinuity_max_bad,
    )
    return PreprocessedFrame(colour=colour, depth=levels[0].depth, levels=levels, colour_mask=mask)


def model_pyramid(
    vertices: np.ndarray, normals: np.ndarray, levels: int
) -> list[tuple[np.ndarray, np.ndarray]]:
    """Downsample raycast vertex/normal maps (any frame) to `levels` levels for ICP.

    Level l+1 takes pixel (2u, 2v) of level l, the pyramid convention of camera.py, so a model
    vertex still projects onto its own pixel with `camera.at_level(l)`. Subsampling never mixes
    a valid point with NaN or blends across depth edges, which averaging would.
    """
    pyramid = [(vertices, normals)]
    for _ in range(1, levels):
        v, n = pyramid[-1]
        height, width = v.shape[0] // 2, v.shape[1] // 2
        pyramid.append((v[: 2 * height : 2, : 2 * width : 2], n[: 2 * height : 2, : 2 * width : 2]))
    return pyramid
