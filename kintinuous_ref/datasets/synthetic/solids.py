"""Solids with closed-form ray intersections: rectangles, boxes (also rooms), cylinders, spheres.

Every solid lives in its own local frame, placed in the world by `pose` (local-to-world 4x4).
Rays are `origin + t * direction` with unnormalised directions: when the directions are the camera's
z = 1 pixel rays (camera.ray_directions), the hit parameter t IS the pixel's depth, and it stays so
after the rigid change of frame into the solid's local coordinates (a linear map keeps t).
`intersect` returns the nearest t > 0 per ray (inf where the ray misses); the face, normal and
texture coordinates of a hit are recovered afterwards from the local hit point by `surface`,
only for the rays the solid actually wins.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass, field

import numpy as np

# Hits closer than this are ignored (the camera never touches a surface; avoids self-hits at t=0).
_MIN_T = 1e-6


def _grid(size_u: float, size_v: float, spacing: float) -> tuple[np.ndarray, np.ndarray]:
    """Vertices (M, 2) in [0, 1]^2 and triangles (K, 3) of a regular grid with cells <= spacing."""
    nu = max(1, int(np.ceil(size_u / spacing)))
    nv = max(1, int(np.ceil(size_v / spacing)))
    s, t = np.meshgrid(np.linspace(0, 1, nu + 1), np.linspace(0, 1, nv + 1), indexing="xy")
    index = np.arange((nu + 1) * (nv + 1)).reshape(nv + 1, nu + 1)
    a, b = index[:-1, :-1].ravel(), index[:-1, 1:].ravel()
    c, d = index[1:, :-1].ravel(), index[1:, 1:].ravel()
    triangles = np.concatenate([np.stack([a, b, d], 1), np.stack([a, d, c], 1)])
    return np.stack([s.ravel(), t.ravel()], axis=1), triangles


@dataclass
class SurfaceMesh:
    """A triangulated solid in its local frame, with what texturing needs per vertex."""

    points: np.ndarray  # (M, 3)
    triangles: np.ndarray  # (K, 3) vertex indices
    face: np.ndarray  # (M,) face index within the solid
    normals: np.ndarray  # (M, 3) local frame, pointing to the visible side
    uv: np.ndarray  # (M, 2) texture coordinates, metres


def _concat(parts: list[SurfaceMesh]) -> SurfaceMesh:
    offsets = np.cumsum([0] + [len(p.points) for p in parts[:-1]])
    return SurfaceMesh(
        points=np.concatenate([p.points for p in parts]),
        triangles=np.concatenate([p.triangles + o for p, o in zip(parts, offsets, strict=True)]),
        face=np.concatenate([p.face for p in parts]),
        normals=np.concatenate([p.normals for p in parts]),
        uv=np.concatenate([p.uv for p in parts]),
    )


@dataclass
class Solid(ABC):
    """A shape in its local frame; `pose` places it in the world (local-to-world)."""

    pose: np.ndarray = field(default_factory=lambda: np.eye(4))

    faces = 1  # distinct surfaces (each gets its own texture)

    @property
    @abstractmethod
    def bounding_radius(self) -> float:
        """Radius of a sphere around the local origin that contains the solid."""

    @abstractmethod
    def intersect(self, origin: np.ndarray, directions: np.ndarray) -> np.ndarray:
        """Nearest hit parameter t > 0 along origin + t d (local frame), inf where missed."""

    @abstractmethod
    def surface(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(face (N,), outward normals (N, 3), uv (N, 2)) of local points on the surface."""

    @abstractmethod
    def mesh(self, spacing: float) -> SurfaceMesh:
        """The surface as triangles no longer than about `spacing` metres."""


@dataclass
class Rectangle(Solid):
    """The rectangle |x| <= half_size[0], |y| <= half_size[1] of the local z = 0 plane."""

    half_size: tuple[float, float] = (0.5, 0.5)

    @property
    def bounding_radius(self) -> float:
        return float(np.hypot(*self.half_size))

    def intersect(self, origin: np.ndarray, directions: np.ndarray) -> np.ndarray:
        with np.errstate(divide="ignore", invalid="ignore"):
            t = -origin[2] / directions[..., 2]  # plane z = 0: o_z + t d_z = 0
        x = origin[0] + t * directions[..., 0]
        y = origin[1] + t * directions[..., 1]
        hit = (t > _MIN_T) & (np.abs(x) <= self.half_size[0]) & (np.abs(y) <= self.half_size[1])
        return np.where(hit, t, np.inf)

    def surface(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        normals = np.zeros_like(points)
        normals[:, 2] = 1.0
        return np.zeros(len(points), np.intp), normals, points[:, :2].copy()

    def mesh(self, spacing: float) -> SurfaceMesh:
        a, b = self.half_size
        st, triangles = _grid(2 * a, 2 * b, spacing)
        uv = (st - 0.5) * [2 * a, 2 * b]
        points = np.column_stack([uv, np.zeros(len(uv))])
        normals = np.tile([0.0, 0.0, 1.0], (len(uv), 1))
        return SurfaceMesh(points, triangles, np.zeros(len(uv), np.intp), normals, uv)


# Box faces: 0 +x, 1 -x, 2 +y, 3 -y, 4 +z, 5 -z; texture axes per face normal axis.
_UV_AXES = {0: (1, 2), 1: (0, 2), 2: (0, 1)}


@dataclass
class Box(Solid):
    """The box |x_i| <= half_size[i]. inside=True: a room, seen from within (normals point in)."""

    half_size: tuple[float, float, float] = (0.5, 0.5, 0.5)
    inside: bool = False

    faces = 6

    @property
    def bounding_radius(self) -> float:
        return np.inf if self.inside else float(np.linalg.norm(self.half_size))

    def intersect(self, origin: np.ndarray, directions: np.ndarray) -> np.ndarray:
        # Slab method: the ray is inside the box for t in [max_i t_enter_i, min_i t_exit_i].
        t_enter = np.full(directions.shape[:-1], -np.inf)
        t_exit = np.full(directions.shape[:-1], np.inf)
        with np.errstate(divide="ignore", invalid="ignore"):
            for axis in range(3):
                inv = 1.0 / directions[..., axis]
                t1 = (-self.half_size[axis] - origin[axis]) * inv
                t2 = (self.half_size[axis] - origin[axis]) * inv
                np.maximum(t_enter, np.minimum(t1, t2), out=t_enter)
                np.minimum(t_exit, np.maximum(t1, t2), out=t_exit)
        if self.inside:  # from within, the visible wall is where the ray leaves the box
            return np.where(t_exit > _MIN_T, t_exit, np.inf)
        hit = (t_enter <= t_exit) & (t_enter > _MIN_T)
        return np.where(hit, t_enter, np.inf)

    def surface(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        half = np.asarray(self.half_size, dtype=np.float64)
        axis = np.argmax(np.abs(points) / half, axis=1)
        rows = np.arange(len(points))
        sign = np.where(points[rows, axis] >= 0, 1.0, -1.0)
        face = 2 * axis + (sign < 0)
        normals = np.zeros_like(points)
        normals[rows, axis] = -sign if self.inside else sign
        u_axis = np.array([_UV_AXES[a][0] for a in range(3)])[axis]
        v_axis = np.array([_UV_AXES[a][1] for a in range(3)])[axis]
        uv = np.stack([points[rows, u_axis], points[rows, v_axis]], axis=1)
        return face, normals, uv

    def mesh(self, spacing: float) -> SurfaceMesh:
        half = np.asarray(self.half_size, dtype=np.float64)
        parts = []
        for face in range(6):
            axis, sign = face // 2, 1.0 - 2.0 * (face % 2)
            ua, va = _UV_AXES[axis]
            st, triangles = _grid(2 * half[ua], 2 * half[va], spacing)
            points = np.zeros((len(st), 3))
            points[:, ua] = (st[:, 0] - 0.5) * 2 * half[ua]
            points[:, va] = (st[:, 1] - 0.5) * 2 * half[va]
            points[:, axis] = sign * half[axis]
            normals = np.zeros_like(points)
            normals[:, axis] = -sign if self.inside else sign
            uv = points[:, [ua, va]]
            parts.append(SurfaceMesh(points, triangles, np.full(len(st), face), normals, uv))
        return _concat(parts)


@dataclass
class Cylinder(Solid):
    """A closed cylinder around the local z axis: x^2 + y^2 <= radius^2, |z| <= half_height."""

    radius: float = 0.1
    half_height: float = 0.1

    faces = 3  # 0 side, 1 top cap, 2 bottom cap

    @property
    def bounding_radius(self) -> float:
        return float(np.hypot(self.radius, self.half_height))

    def intersect(self, origin: np.ndarray, directions: np.ndarray) -> np.ndarray:
        dx, dy, dz = directions[..., 0], directions[..., 1], directions[..., 2]
        ox, oy, oz = origin
        # side: (o_xy + t d_xy)^2 = r^2, a t^2 + 2 b t + c = 0, the smaller root enters
        a = dx * dx + dy * dy
        b = ox * dx + oy * dy
        c = ox * ox + oy * oy - self.radius**2
        disc = b * b - a * c
        with np.errstate(divide="ignore", invalid="ignore"):
            t_side = (-b - np.sqrt(np.maximum(disc, 0.0))) / a
            side_ok = (
                (disc >= 0) & (t_side > _MIN_T) & (np.abs(oz + t_side * dz) <= self.half_height)
            )
            best = np.where(side_ok, t_side, np.inf)
            for cap in (self.half_height, -self.half_height):
                t_cap = (cap - oz) / dz
                x, y = ox + t_cap * dx, oy + t_cap * dy
                cap_ok = (t_cap > _MIN_T) & (x * x + y * y <= self.radius**2)
                best = np.where(cap_ok & (t_cap < best), t_cap, best)
        return best

    def surface(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        radial = np.hypot(points[:, 0], points[:, 1])
        on_cap = np.abs(self.half_height - np.abs(points[:, 2])) < np.abs(self.radius - radial)
        face = np.where(on_cap, np.where(points[:, 2] > 0, 1, 2), 0)
        normals = np.zeros_like(points)
        with np.errstate(divide="ignore", invalid="ignore"):
            normals[:, 0] = points[:, 0] / radial
            normals[:, 1] = points[:, 1] / radial
        normals[on_cap] = 0.0
        normals[on_cap, 2] = np.sign(points[on_cap, 2])
        angle_length = self.radius * np.arctan2(points[:, 1], points[:, 0])
        uv = np.where(on_cap[:, None], points[:, :2], np.stack([angle_length, points[:, 2]], 1))
        return face, normals, uv

    def mesh(self, spacing: float) -> SurfaceMesh:
        r, h = self.radius, self.half_height
        st, triangles = _grid(2 * np.pi * r, 2 * h, spacing)
        angle = (st[:, 0] - 0.5) * 2 * np.pi
        points = np.column_stack([r * np.cos(angle), r * np.sin(angle), (st[:, 1] - 0.5) * 2 * h])
        normals = np.column_stack([np.cos(angle), np.sin(angle), np.zeros(len(st))])
        uv = np.column_stack([r * angle, points[:, 2]])
        parts = [SurfaceMesh(points, triangles, np.zeros(len(st), np.intp), normals, uv)]
        for face, z in ((1, h), (2, -h)):  # caps: polar grids (radius x angle)
            st, triangles = _grid(r, 2 * np.pi * r, spacing)
            angle = st[:, 1] * 2 * np.pi
            xy = np.column_stack([st[:, 0] * r * np.cos(angle), st[:, 0] * r * np.sin(angle)])
            cap = np.column_stack([xy, np.full(len(st), z)])
            normals = np.tile([0.0, 0.0, np.sign(z)], (len(st), 1))
            parts.append(SurfaceMesh(cap, triangles, np.full(len(st), face), normals, xy))
        return _concat(parts)


@dataclass
class Sphere(Solid):
    """The sphere of `radius` around the local origin."""

    radius: float = 0.1

    @property
    def bounding_radius(self) -> float:
        return self.radius

    def intersect(self, origin: np.ndarray, directions: np.ndarray) -> np.ndarray:
        a = np.einsum("...i,...i->...", directions, directions)
        b = np.einsum("...i,i->...", directions, origin)
        c = origin @ origin - self.radius**2
        disc = b * b - a * c
        t = (-b - np.sqrt(np.maximum(disc, 0.0))) / a
        return np.where((disc >= 0) & (t > _MIN_T), t, np.inf)

    def surface(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        normals = points / np.linalg.norm(points, axis=1, keepdims=True)
        longitude = np.arctan2(normals[:, 1], normals[:, 0])
        latitude = np.arcsin(np.clip(normals[:, 2], -1.0, 1.0))
        uv = self.radius * np.stack([longitude, latitude], axis=1)
        return np.zeros(len(points), np.intp), normals, uv

    def mesh(self, spacing: float) -> SurfaceMesh:
        r = self.radius
        st, triangles = _grid(2 * np.pi * r, np.pi * r, spacing)
        longitude = (st[:, 0] - 0.5) * 2 * np.pi
        latitude = (st[:, 1] - 0.5) * np.pi
        normals = np.column_stack(
            [
                np.cos(latitude) * np.cos(longitude),
                np.cos(latitude) * np.sin(longitude),
                np.sin(latitude),
            ]
        )
        uv = r * np.column_stack([longitude, latitude])
        return SurfaceMesh(r * normals, triangles, np.zeros(len(st), np.intp), normals, uv)
