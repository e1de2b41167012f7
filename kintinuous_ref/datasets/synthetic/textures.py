"""Procedural, world-anchored surface textures with detail at several scales.

Photometric odometry (paper IV-A) needs image gradients at every pyramid level, so each surface gets
multi-octave value noise (wavelengths from about a metre down to a centimetre), optional blobs
(thresholded low-frequency noise, sharp-edged spots) and optional lines (tile grout or planks), all
evaluated from the surface's own 2D coordinates in metres. The texture is therefore identical from
any viewpoint. Octaves finer than the pixel footprint are faded to their mean (a cheap mip-map),
so distant surfaces do not alias and flicker from frame to frame.
"""

from __future__ import annotations

import colorsys
from dataclasses import dataclass
from functools import lru_cache

import cv2
import numpy as np

TILE_SIZE = 256  # texels per side of the periodic noise tile
TILE_WAVELENGTH = 16.0  # texels per noise wavelength inside the tile
OCTAVES = 7  # wavelengths base, base/2, ..., base/64
_REMAP_WIDTH = 1024


@lru_cache(maxsize=1)
def noise_tile() -> np.ndarray:
    """A periodic, band-limited noise image (TILE_SIZE^2 float32, uniform in [0, 1]).

    White noise keeps only spatial frequencies up to TILE_SIZE / TILE_WAVELENGTH cycles per tile
    (a smooth FFT low-pass, hence seamlessly periodic), then is equalised to a uniform histogram
    so every octave has full contrast. Fixed seed: textures differ per surface through offsets,
    rotations and palettes, not through the tile.
    """
    rng = np.random.default_rng(20130506)
    white = rng.standard_normal((TILE_SIZE, TILE_SIZE))
    freq = np.fft.fftfreq(TILE_SIZE) * TILE_SIZE  # cycles per tile
    radius = np.hypot(freq[:, None], freq[None, :])
    cutoff = TILE_SIZE / TILE_WAVELENGTH
    lowpass = np.exp(-0.5 * (radius / (0.5 * cutoff)) ** 2)
    smooth = np.real(np.fft.ifft2(np.fft.fft2(white) * lowpass))
    ranks = np.argsort(np.argsort(smooth, axis=None))
    return ((ranks + 0.5) / ranks.size).reshape(TILE_SIZE, TILE_SIZE).astype(np.float32)


def wrap(x: np.ndarray) -> np.ndarray:
    """Texel coordinates moved into [0, TILE_SIZE) (the tile is periodic), float32."""
    x = np.asarray(x, dtype=np.float32)
    return x - np.floor(x * np.float32(1.0 / TILE_SIZE)) * np.float32(TILE_SIZE)


def _wrap_in_place(x: np.ndarray) -> None:
    x -= np.floor(x * np.float32(1.0 / TILE_SIZE)) * np.float32(TILE_SIZE)


class _TileSampler:
    """Bilinear lookups of the periodic tile for a fixed number of points.

    cv2.remap wants 2D maps below 32767 rows and columns, so the points' coordinates live in
    padded (rows, 1024) buffers `x`, `y`. They must lie inside the tile: remap handles
    BORDER_WRAP correctly beyond it, but ten times slower.
    """

    def __init__(self, count: int) -> None:
        self.count = count
        rows = max(1, -(-count // _REMAP_WIDTH))
        self._x = np.zeros((rows, _REMAP_WIDTH), dtype=np.float32)
        self._y = np.zeros((rows, _REMAP_WIDTH), dtype=np.float32)
        self.x = self._x.reshape(-1)[:count]  # views: write coordinates here
        self.y = self._y.reshape(-1)[:count]

    def sample(self) -> np.ndarray:
        values = cv2.remap(
            noise_tile(), self._x, self._y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_WRAP
        )
        return values.reshape(-1)[: self.count]

    def __call__(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Samples at texel coordinates x, y (any values)."""
        self.x[:] = x
        self.y[:] = y
        _wrap_in_place(self.x)
        _wrap_in_place(self.y)
        return self.sample()


@dataclass(frozen=True)
class Material:
    """How one surface looks. Lengths in metres of the surface's (u, v) coordinates."""

    palette: np.ndarray  # (3, 3) RGB in [0, 1]: noise value 0 -> 0.5 -> 1 maps through these
    wavelength: float = 0.6  # longest noise wavelength
    persistence: float = 0.75  # amplitude ratio of successive octaves
    contrast: float = 2.2  # stretch of the (averaged, hence flat) octave sum around 0.5
    blob_colour: np.ndarray | None = None  # (3,) RGB of sharp-edged spots, None: no spots
    blob_wavelength: float = 0.3
    blob_cover: float = 0.25  # fraction of the surface the spots cover
    vein_width: float = 0.02  # half-width of the veins in noise units (0..1)
    vein_darkness: float = 0.0  # vein colour = base * (1 - vein_darkness); 0: no veins
    lines: str = "none"  # "none" | "grid" (tiles) | "stripes" (planks, along u)
    line_period: float = 0.3
    line_width: float = 0.006
    line_darkness: float = 0.6  # line colour = base * (1 - line_darkness)


@dataclass
class MaterialTable:
    """The materials of every surface of a scene stacked into arrays indexed by surface id."""

    lut: np.ndarray  # (S, 256, 3) float32 palette look-up tables
    offsets: np.ndarray  # (S, 2) texel offsets, so equal materials still differ per surface
    rotation: np.ndarray  # (S,) angle of the texture on the surface
    wavelength: np.ndarray  # (S,)
    persistence: np.ndarray
    contrast: np.ndarray
    blob_colour: np.ndarray  # (S, 3)
    blob_amount: np.ndarray  # (S,) 0 or 1
    blob_wavelength: np.ndarray
    blob_threshold: np.ndarray
    vein_width: np.ndarray
    vein_darkness: np.ndarray
    line_kind: np.ndarray  # (S,) 0 none, 1 grid, 2 stripes
    line_period: np.ndarray
    line_width: np.ndarray
    line_darkness: np.ndarray


def _palette_lut(palette: np.ndarray) -> np.ndarray:
    levels = np.linspace(0.0, 1.0, 256)
    knots = np.array([0.0, 0.5, 1.0])
    return np.stack([np.interp(levels, knots, palette[:, c]) for c in range(3)], axis=-1)


def build_table(materials: list[Material], rng: np.random.Generator) -> MaterialTable:
    """Stack per-surface materials; each surface gets its own random texture offset and angle."""
    count = len(materials)
    kinds = {"none": 0, "grid": 1, "stripes": 2}
    table = MaterialTable(
        lut=np.stack([_palette_lut(m.palette) for m in materials]).astype(np.float32),
        offsets=rng.uniform(0, TILE_SIZE, (count, 2)),
        rotation=np.array([0.0 if m.lines != "none" else rng.uniform(0, np.pi) for m in materials]),
        wavelength=np.array([m.wavelength for m in materials]),
        persistence=np.array([m.persistence for m in materials]),
        contrast=np.array([m.contrast for m in materials]),
        blob_colour=np.array(
            [m.blob_colour if m.blob_colour is not None else np.zeros(3) for m in materials]
        ),
        blob_amount=np.array([0.0 if m.blob_colour is None else 1.0 for m in materials]),
        blob_wavelength=np.array([m.blob_wavelength for m in materials]),
        # uniform noise values: the spots cover `blob_cover` of the surface above this threshold
        blob_threshold=np.array([1.0 - m.blob_cover for m in materials]),
        vein_width=np.array([m.vein_width for m in materials]),
        vein_darkness=np.array([m.vein_darkness for m in materials]),
        line_kind=np.array([kinds[m.lines] for m in materials]),
        line_period=np.array([m.line_period for m in materials]),
        line_width=np.array([m.line_width for m in materials]),
        line_darkness=np.array([m.line_darkness for m in materials]),
    )
    # float32 throughout: texture arithmetic runs on every pixel, and 1e-7 relative is plenty
    for name, values in vars(table).items():
        if values.dtype == np.float64:
            setattr(table, name, values.astype(np.float32))
    return table


def _octave_noise(
    u: np.ndarray,
    v: np.ndarray,
    reach: np.ndarray,
    persistence: np.ndarray,
    sampler: _TileSampler,
) -> np.ndarray:
    """Sum of OCTAVES value-noise octaves, normalised to [0, 1] around its mean 0.5.

    u, v: coordinates in octave-0 texels (already offset per surface). Octave k samples the tile
    at 2^k (u, v) + c_k (c_k = 2 c_(k-1) + (37, 91): each octave its own part of the tile), i.e.
    at wavelength / 2^k, with amplitude persistence^k. The coordinates are doubled in place and
    kept inside the tile, which repeats itself.
    reach = wavelength / (2 footprint): the octave's fade weight is clip(reach / 2^k - 1, 0, 1),
    1 at four or more pixels per period and 0 at two or fewer (Nyquist), where it contributes
    its mean instead (a cheap mip-map: no aliasing, no flicker from frame to frame).
    """
    total = np.zeros_like(reach)
    amplitude = np.ones_like(reach)
    sampler.x[:] = u
    sampler.y[:] = v
    for k in range(OCTAVES):
        fade = np.clip(reach * np.float32(0.5**k) - 1.0, 0.0, 1.0)
        if not fade.any():
            break  # finer octaves fade even sooner
        if k > 0:
            for coordinate, shift in ((sampler.x, 37.0), (sampler.y, 91.0)):
                coordinate *= np.float32(2.0)
                coordinate += np.float32(shift)
        _wrap_in_place(sampler.x)
        _wrap_in_place(sampler.y)
        total += amplitude * fade * (sampler.sample() - np.float32(0.5))
        amplitude *= persistence
    # normalise by the sum of all amplitudes, faded or not, so that fading keeps the contrast
    amplitude_sum = (1.0 - persistence**OCTAVES) / (1.0 - persistence)
    return np.float32(0.5) + total / amplitude_sum


def _line_mask(
    coordinate: np.ndarray, period: np.ndarray, width: np.ndarray, footprint: np.ndarray
) -> np.ndarray:
    """Coverage in [0, 1] of lines of `width` every `period`, box-filtered over the footprint."""
    distance = np.abs(coordinate - period * np.round(coordinate / period))
    effective = np.maximum(width, footprint)
    edge = np.clip(0.5 + (effective / 2.0 - distance) / footprint, 0.0, 1.0)
    # wider than the line itself when the pixel is: keep the mean coverage width / period
    return edge * (width / effective)


def evaluate(
    table: MaterialTable, surface: np.ndarray, uv: np.ndarray, footprint: np.ndarray
) -> np.ndarray:
    """Albedo (N, 3) float32 in [0, 1] of points `uv` (N, 2, metres) on surfaces `surface` (N,).

    `footprint` (N,) is the size of one pixel on the surface in metres (for anti-aliasing).
    """
    surface = np.asarray(surface)

    def per_point(values: np.ndarray) -> np.ndarray:
        return np.take(values, surface, axis=0)

    footprint = np.maximum(np.asarray(footprint, dtype=np.float32), np.float32(1e-6))
    u0, v0 = uv[:, 0].astype(np.float32), uv[:, 1].astype(np.float32)
    cos_r, sin_r = per_point(np.cos(table.rotation)), per_point(np.sin(table.rotation))
    u_rot, v_rot = cos_r * u0 - sin_r * v0, sin_r * u0 + cos_r * v0
    sampler = _TileSampler(len(surface))
    offset = per_point(table.offsets)

    to_texels = per_point(np.float32(TILE_WAVELENGTH) / table.wavelength)
    reach = per_point(table.wavelength / 2) / footprint
    noise = _octave_noise(
        u_rot * to_texels + offset[:, 0],
        v_rot * to_texels + offset[:, 1],
        reach,
        per_point(table.persistence),
        sampler,
    )
    # veins: thin dark iso-lines of the noise at its median, wiggly at every octave's scale
    veins = np.clip(1.0 - np.abs(noise - 0.5) / per_point(table.vein_width), 0.0, 1.0)
    noise = np.clip(0.5 + per_point(table.contrast) * (noise - 0.5), 0.0, 1.0)
    palette_index = surface * 256 + (noise * 255.0).astype(np.intp)
    albedo = np.take(table.lut.reshape(-1, 3), palette_index, axis=0)
    albedo *= (1.0 - per_point(table.vein_darkness) * veins)[:, None]

    # blobs: one more low-frequency noise sample, thresholded with a footprint-wide soft edge
    if np.any(table.blob_amount[np.unique(surface)] > 0):
        blob_lam = per_point(table.blob_wavelength)
        to_texels = np.float32(TILE_WAVELENGTH) / blob_lam
        blob_noise = sampler(u_rot * to_texels + offset[:, 1], v_rot * to_texels + offset[:, 0])
        softness = np.float32(0.01) + np.float32(0.5) * footprint / blob_lam
        blob = np.clip((blob_noise - per_point(table.blob_threshold)) / softness + 0.5, 0.0, 1.0)
        blob *= per_point(table.blob_amount)
        albedo += (per_point(table.blob_colour) - albedo) * blob[:, None]

    # lines: grid = grout along u and v (tiles), stripes = joints across v (planks)
    kind = per_point(table.line_kind)
    if kind.any():
        width = np.where(kind > 0, per_point(table.line_width), 0.0).astype(np.float32)
        period = per_point(table.line_period)
        lines = _line_mask(v0, period, width, footprint)
        grid = np.where(kind == 1, width, 0.0).astype(np.float32)
        lines = np.maximum(lines, _line_mask(u0, period, grid, footprint))
        albedo *= (1.0 - per_point(table.line_darkness) * lines)[:, None]
    return albedo


def random_material(rng: np.random.Generator, kind: str) -> Material:
    """A plausible material of a kind: "wall", "floor", "wood", "object" or "ceiling"."""

    def colour(hue: float, saturation: float, value: float) -> np.ndarray:
        return np.array(colorsys.hsv_to_rgb(hue % 1.0, np.clip(saturation, 0, 1), value))

    hue = rng.uniform()
    if kind == "floor":
        sat, val = rng.uniform(0.2, 0.5), rng.uniform(0.45, 0.7)
        palette = np.stack(
            [
                colour(hue, sat, val * 0.55),
                colour(hue + 0.03, sat, val),
                colour(hue + 0.06, sat * 0.7, min(1.0, val * 1.35)),
            ]
        )
        return Material(
            palette,
            wavelength=rng.uniform(0.4, 0.8),
            lines="grid",
            line_period=rng.choice([0.3, 0.4, 0.5]),
            line_width=0.008,
            blob_colour=colour(hue + 0.5, 0.3, 0.35),
            blob_wavelength=0.5,
            blob_cover=0.12,
            vein_darkness=0.3,
        )
    if kind == "wood":
        hue = rng.uniform(0.05, 0.11)
        palette = np.stack([colour(hue, 0.7, 0.3), colour(hue, 0.6, 0.55), colour(hue, 0.45, 0.8)])
        return Material(
            palette,
            wavelength=rng.uniform(0.3, 0.5),
            persistence=0.75,
            lines="stripes",
            line_period=rng.uniform(0.1, 0.18),
            line_width=0.004,
            line_darkness=0.5,
        )
    if kind in ("wall", "ceiling"):
        sat, val = rng.uniform(0.1, 0.35), rng.uniform(0.6, 0.85)
        palette = np.stack(
            [
                colour(hue, sat, val * 0.5),
                colour(hue, sat * 0.8, val),
                colour(hue + 0.1, sat * 0.5, min(1.0, val * 1.25)),
            ]
        )
        return Material(
            palette,
            wavelength=rng.uniform(0.6, 1.2),
            persistence=0.8,
            blob_colour=colour(hue + rng.uniform(0.3, 0.7), 0.6, 0.5),
            blob_wavelength=rng.uniform(0.4, 0.9),
            blob_cover=0.15,
            vein_darkness=0.45,
        )
    sat, val = rng.uniform(0.45, 0.9), rng.uniform(0.5, 0.9)
    palette = np.stack(
        [
            colour(hue, sat, val * 0.35),
            colour(hue + 0.05, sat, val),
            colour(hue + 0.12, sat * 0.6, min(1.0, val * 1.3)),
        ]
    )
    return Material(
        palette,
        wavelength=rng.uniform(0.15, 0.4),
        persistence=0.75,
        blob_colour=colour(hue + 0.5, 0.8, rng.uniform(0.2, 0.9)),
        blob_wavelength=rng.uniform(0.08, 0.2),
        blob_cover=0.2,
        vein_darkness=0.5,
    )
