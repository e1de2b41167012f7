"""A scene = solids + their materials + a light; ray casting it gives exact depth and colour.

Rendering (vectorised over pixels, looped over the few dozen solids): every solid intersects the
pixel rays that can reach it (those inside the image rectangle its bounding sphere projects to),
the nearest hit per pixel wins (a z-buffer over closed-form intersections), and only then are
normals, texture coordinates and colours computed, once per pixel.
Shading is Lambertian under a fixed world light, so it does not depend on the viewpoint: a surface
point has the same colour from every camera pose (the brightness constancy that RGB-D odometry
assumes, paper IV-A).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from kintinuous_ref import se3
from kintinuous_ref.camera import Intrinsics
from kintinuous_ref.datasets.synthetic import textures
from kintinuous_ref.datasets.synthetic.solids import Solid


@dataclass
class RayHits:
    """What the rays of one camera hit: exact depth, and per hit pixel its surface point."""

    depth: np.ndarray  # (H, W) float64 z-depth, inf where nothing is hit
    cos_incidence: np.ndarray  # (H, W) |cos| of the angle between ray and normal; 0: no hit
    pixels: np.ndarray  # (M,) flat indices of the pixels that hit something
    surface: np.ndarray  # (M,) global surface id of each hit
    uv: np.ndarray  # (M, 2) texture coordinates (metres on the surface)
    light: np.ndarray  # (M,) cosine between the light and the (camera-facing) normal


def rotate(points: np.ndarray, rotation: np.ndarray) -> np.ndarray:
    """rotation @ p for points (..., 3), written out per column.

    (N, 3) @ (3, 3) goes to a multi-threaded BLAS that is many times slower than this on a busy
    machine; three scaled columns are predictable.
    """
    return (
        points[..., 0:1] * rotation[:, 0]
        + points[..., 1:2] * rotation[:, 1]
        + points[..., 2:3] * rotation[:, 2]
    )


def _rotated_rays(rotation: np.ndarray, ray_x: np.ndarray, ray_y: np.ndarray) -> np.ndarray:
    """rotation @ (x_u, y_v, 1) for a grid of rays (rows ray_y, columns ray_x), (h, w, 3).

    Separable, so each component is one outer sum: far cheaper than rotating every ray.
    """
    directions = np.empty((len(ray_y), len(ray_x), 3))
    for k in range(3):
        np.add(
            rotation[k, 0] * ray_x[None, :],
            rotation[k, 1] * ray_y[:, None] + rotation[k, 2],
            out=directions[..., k],
        )
    return directions


def _rigid_inverse(pose: np.ndarray) -> np.ndarray:
    inverse = np.eye(4)
    inverse[:3, :3] = pose[:3, :3].T
    inverse[:3, 3] = -pose[:3, :3].T @ pose[:3, 3]
    return inverse


@dataclass
class Scene:
    """Solids with one material per face, a directional light and a background colour."""

    solids: list[Solid]
    materials: list[list[textures.Material]]  # per solid, per face
    seed: int = 0
    light_direction: np.ndarray = field(
        default_factory=lambda: np.array([0.4, 0.25, 1.0]) / np.linalg.norm([0.4, 0.25, 1.0])
    )
    ambient: float = 0.6  # shade = ambient + (1 - ambient) max(0, n . l)
    background: tuple[float, float, float] = (0.0, 0.0, 0.0)

    def __post_init__(self) -> None:
        if len(self.materials) != len(self.solids):
            raise ValueError("one list of materials per solid")
        for solid in self.solids:
            se3.check_pose(solid.pose)
        self.surface_offsets = np.cumsum([0] + [s.faces for s in self.solids])
        self._local_from_world = [_rigid_inverse(s.pose) for s in self.solids]
        flat = []
        for solid, mats in zip(self.solids, self.materials, strict=True):
            if len(mats) not in (1, solid.faces):
                raise ValueError(f"{type(solid).__name__} needs 1 or {solid.faces} materials")
            flat.extend(mats * solid.faces if len(mats) == 1 else mats)
        self.table = textures.build_table(flat, np.random.default_rng([self.seed, 7]))

    def raycast(self, camera: Intrinsics, pose: np.ndarray) -> RayHits:
        """Exact nearest hits of all pixel rays of `camera` at camera-to-world `pose`."""
        height, width = camera.height, camera.width
        # pixel (u, v) has the ray (x_u, y_v, 1) (camera.ray_directions): with z = 1 the hit
        # parameter is the depth; x depends on the column only, y on the row only
        ray_x = (np.arange(width) - camera.cx) / camera.fx
        ray_y = (np.arange(height) - camera.cy) / camera.fy
        depth = np.full((height, width), np.inf)
        # int16 owners: numpy's stable argsort is then a radix sort (linear time)
        winner = np.full((height, width), -1, dtype=np.int16)
        local_from_camera = []
        for index, solid in enumerate(self.solids):
            transform = self._local_from_world[index] @ pose  # camera frame -> solid frame
            local_from_camera.append(transform)
            window = _pixel_window(solid, transform, camera)
            if window is None:
                continue
            rows, cols = window
            directions = _rotated_rays(transform[:3, :3], ray_x[cols], ray_y[rows])
            t = solid.intersect(transform[:3, 3], directions)
            closer = t < depth[rows, cols]
            np.copyto(depth[rows, cols], t, where=closer)
            np.copyto(winner[rows, cols], index, where=closer)

        # Surface attributes, once per hit pixel, grouped by the solid that won it.
        pixels = np.flatnonzero(winner >= 0)
        owners = winner.ravel()[pixels]
        order = np.argsort(owners, kind="stable")
        pixels, owners = pixels[order], owners[order]
        hit_depth = depth.ravel()[pixels]
        hit_x, hit_y = ray_x[pixels % width], ray_y[pixels // width]
        camera_points = np.stack([hit_x * hit_depth, hit_y * hit_depth, hit_depth], axis=1)
        # |camera point| = depth |ray|, for the angle of incidence
        distance = hit_depth * np.sqrt(1.0 + hit_x**2 + hit_y**2)
        surface = np.empty(len(pixels), dtype=np.intp)
        uv = np.empty((len(pixels), 2))
        light = np.empty(len(pixels))
        cos_incidence = np.zeros(height * width)
        starts = np.flatnonzero(np.r_[True, owners[1:] != owners[:-1]]) if len(owners) else []
        for first, last in zip(starts, [*starts[1:], len(owners)], strict=True):
            index = owners[first]
            solid, transform = self.solids[index], local_from_camera[index]
            eye = transform[:3, 3]  # the camera centre in the solid's frame
            view = rotate(camera_points[first:last], transform[:3, :3])  # eye -> hit, local
            face, normals, uv[first:last] = solid.surface(view + eye)
            surface[first:last] = self.surface_offsets[index] + face
            # Face the camera (rectangles are two-sided): flip normals that point along the ray.
            along = np.einsum("ni,ni->n", normals, view)
            normals *= np.where(along > 0, -1.0, 1.0)[:, None]
            cos_incidence[pixels[first:last]] = np.abs(along) / distance[first:last]
            light_in_solid = solid.pose[:3, :3].T @ self.light_direction
            light[first:last] = np.einsum("ni,i->n", normals, light_in_solid)
        return RayHits(depth, cos_incidence.reshape(height, width), pixels, surface, uv, light)

    def shade(self, hits: RayHits, footprint: np.ndarray) -> np.ndarray:
        """Colour (H, W, 3) float32 in [0, 1] of the hit surfaces (albedo x Lambertian light).

        `footprint` (M,): metres per pixel on the surface at each hit (texture anti-aliasing).
        """
        height, width = hits.depth.shape
        colour = np.empty((height * width, 3), dtype=np.float32)
        colour[:] = self.background
        albedo = textures.evaluate(self.table, hits.surface, hits.uv, footprint)
        colour[hits.pixels] = albedo * self._shade(hits.light)[:, None]
        return colour.reshape(height, width, 3)

    def _shade(self, cos_light: np.ndarray) -> np.ndarray:
        return (self.ambient + (1.0 - self.ambient) * np.maximum(cos_light, 0.0)).astype(np.float32)

    def colour_at(
        self, surface: np.ndarray, uv: np.ndarray, normals: np.ndarray, footprint: float
    ) -> np.ndarray:
        """Colour (N, 3) float32 of surface points (world normals) seen at a footprint (metres)."""
        footprint = np.full(len(surface), footprint, dtype=np.float32)
        albedo = textures.evaluate(self.table, surface, uv, footprint)
        return albedo * self._shade(np.einsum("ni,i->n", normals, self.light_direction))[:, None]


def _pixel_window(
    solid: Solid, local_from_camera: np.ndarray, camera: Intrinsics
) -> tuple[slice, slice] | None:
    """Rows and columns of the pixels whose rays can hit `solid` (a conservative rectangle).

    The solid lies inside a sphere; the sphere lies inside an axis-aligned cube in the camera frame,
    and x/z, y/z over that cube are extreme at its corners. None: the sphere is entirely outside
    the viewing frustum (behind the camera or beside the image).
    """
    full = (slice(0, camera.height), slice(0, camera.width))
    radius = solid.bounding_radius
    if not np.isfinite(radius):
        return full
    camera_from_local = _rigid_inverse(local_from_camera)
    centre = camera_from_local[:3, 3]
    if centre[2] + radius <= 0:
        return None
    # the four side planes of the frustum pass through the camera centre and the image borders
    x_min, x_max = (-0.5 - camera.cx) / camera.fx, (camera.width - 0.5 - camera.cx) / camera.fx
    y_min, y_max = (-0.5 - camera.cy) / camera.fy, (camera.height - 0.5 - camera.cy) / camera.fy
    for inward in ((1.0, 0.0, -x_min), (-1.0, 0.0, x_max), (0.0, 1.0, -y_min), (0.0, -1.0, y_max)):
        normal = np.asarray(inward)
        if normal @ centre < -radius * np.linalg.norm(normal):
            return None
    if centre[2] - radius <= 1e-3:
        return full
    z_near, z_far = centre[2] - radius, centre[2] + radius
    bounds = []
    for axis, focal, principal, size in (
        (0, camera.fx, camera.cx, camera.width),
        (1, camera.fy, camera.cy, camera.height),
    ):
        low, high = centre[axis] - radius, centre[axis] + radius
        ratios = [low / z_near, low / z_far, high / z_near, high / z_far]
        first = int(np.floor(focal * min(ratios) + principal))
        last = int(np.ceil(focal * max(ratios) + principal))
        first, last = max(first, 0), min(last + 1, size)
        if first >= last:
            return None
        bounds.append(slice(first, last))
    return bounds[1], bounds[0]
