"""The five scenarios: scene layouts and camera paths (world z up, metres, seconds).

Each builder returns the scene, the base camera path (times -> positions, viewing directions) and
the light level per frame. Layouts are fixed; the seed changes textures, colours, the tremor and,
in `loop`, the objects along the walls.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from kintinuous_ref.datasets.synthetic.scene import Scene
from kintinuous_ref.datasets.synthetic.solids import Box, Cylinder, Rectangle, Solid, Sphere
from kintinuous_ref.datasets.synthetic.textures import Material, random_material
from kintinuous_ref.datasets.synthetic.trajectories import FRAME_RATE, PathFunction, direction

DARK_LEVEL = 0.02  # light level while the light is out in `dark`
LOOP_LAP_SECONDS = 28.0  # one lap of the `loop` path (840 frames, 12.1 m)


def placed(x: float, y: float, z: float, yaw_deg: float = 0.0) -> np.ndarray:
    """Local-to-world pose: a rotation about world z, then a translation."""
    c, s = np.cos(np.radians(yaw_deg)), np.sin(np.radians(yaw_deg))
    pose = np.eye(4)
    pose[:3, :3] = [[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]
    pose[:3, 3] = (x, y, z)
    return pose


def _wave(times: np.ndarray, amplitude: float, period: float, phase: float = 0.0) -> np.ndarray:
    return amplitude * np.sin(2 * np.pi * times / period + phase)


class _Builder:
    """Collects solids with their materials."""

    def __init__(self, rng: np.random.Generator) -> None:
        self.rng = rng
        self.solids: list[Solid] = []
        self.materials: list[list[Material]] = []

    def add(self, solid: Solid, kind: str | list[str] = "object") -> None:
        kinds = [kind] if isinstance(kind, str) else kind
        self.solids.append(solid)
        self.materials.append([random_material(self.rng, k) for k in kinds])

    def room(self, half: tuple[float, float, float], centre: tuple[float, float, float]) -> None:
        """A room seen from inside: four walls, ceiling (+z face), floor (-z face)."""
        self.add(
            Box(placed(*centre), half, inside=True),
            ["wall", "wall", "wall", "wall", "ceiling", "floor"],
        )

    def scene(self, seed: int) -> Scene:
        return Scene(self.solids, self.materials, seed=seed)


def _furnished_room(rng: np.random.Generator, seed: int) -> Scene:
    """A 5 x 4.4 m room: a table with objects in the middle, furniture along the walls."""
    b = _Builder(rng)
    b.room((2.5, 2.2, 1.35), (0.0, 0.0, 1.35))
    # table: top at 0.76 m, four legs
    b.add(Box(placed(0.0, 0.0, 0.74), (0.8, 0.45, 0.02)), "wood")
    for sx in (-1, 1):
        for sy in (-1, 1):
            b.add(Box(placed(sx * 0.74, sy * 0.39, 0.36), (0.03, 0.03, 0.36)), "wood")
    # on the table
    b.add(Box(placed(-0.45, 0.1, 0.80, 20), (0.12, 0.09, 0.04)))  # books
    b.add(Box(placed(0.35, -0.15, 0.86, -30), (0.1, 0.1, 0.1)))  # a box
    b.add(Cylinder(placed(0.05, 0.22, 0.815), 0.045, 0.055))  # mug
    b.add(Cylinder(placed(0.55, 0.25, 0.89), 0.035, 0.13))  # bottle
    b.add(Sphere(placed(-0.15, -0.2, 0.85), 0.09))  # ball
    b.add(Box(placed(-0.1, 0.36, 1.06), (0.28, 0.015, 0.18)))  # monitor
    b.add(Cylinder(placed(-0.1, 0.36, 0.82), 0.02, 0.06))  # its stand
    # furniture
    b.add(Box(placed(2.2, 0.8, 0.5), (0.25, 0.5, 0.5)), "wood")  # cabinet
    b.add(Box(placed(-1.2, 2.0, 0.9), (0.6, 0.18, 0.9)), "wood")  # shelf
    b.add(Box(placed(0.0, -0.8, 0.45), (0.22, 0.22, 0.025)))  # chair seat
    b.add(Box(placed(0.0, -1.0, 0.7), (0.22, 0.02, 0.22)))  # chair back
    b.add(Cylinder(placed(0.0, -0.8, 0.21), 0.03, 0.21))  # chair pedestal
    b.add(Cylinder(placed(-2.0, -1.7, 0.3), 0.15, 0.3))  # plant pot
    b.add(Sphere(placed(-2.0, -1.7, 0.85), 0.3))  # plant
    b.add(Sphere(placed(1.5, -1.6, 0.15), 0.15))  # ball on the floor
    b.add(Box(placed(1.0, 2.15, 1.5), (0.5, 0.04, 0.35)))  # picture frame on the +y wall
    return b.scene(seed)


def _orbit_path(phase: float, sweep: float, period: float) -> PathFunction:
    """Around the table on an ellipse (1.7 x 1.45 m), looking at a wandering point above it."""

    def path(times: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        angle = phase + (
            sweep * np.sin(2 * np.pi * times / period) if sweep else 2 * np.pi * times / period
        )
        positions = np.stack(
            [1.7 * np.cos(angle), 1.45 * np.sin(angle), 1.45 + _wave(times, 0.12, 9.0)], axis=-1
        )
        targets = np.stack(
            [_wave(times, 0.15, 13.0), _wave(times, 0.1, 17.0, 1.0), 0.8 + _wave(times, 0.05, 7.0)],
            axis=-1,
        )
        return positions, targets - positions

    return path


def desk(
    rng: np.random.Generator, seed: int, frames: int
) -> tuple[Scene, PathFunction, np.ndarray]:
    """Back and forth around a table, 0.1-0.35 m/s."""
    return _furnished_room(rng, seed), _orbit_path(-np.pi / 2, 0.8, 24.0), np.ones(frames)


def dark(
    rng: np.random.Generator, seed: int, frames: int
) -> tuple[Scene, PathFunction, np.ndarray]:
    """A slow orbit (40 s per turn) of the furnished room; frames N/3..2N/3 in near darkness."""
    light = np.ones(frames)
    light[frames // 3 : (2 * frames) // 3] = DARK_LEVEL
    return _furnished_room(rng, seed), _orbit_path(np.pi / 2, 0.0, 40.0), light


def corridor(
    rng: np.random.Generator, seed: int, frames: int
) -> tuple[Scene, PathFunction, np.ndarray]:
    """Walking 0.35 m/s along a 2.2 m wide corridor of plain textured planes, looking at a wall."""
    speed, behind, ahead = 0.35, 3.0, 7.0
    length = behind + speed * frames / FRAME_RATE + ahead  # the end walls stay beyond 4 m
    b = _Builder(rng)
    b.room((length / 2, 1.1, 1.3), (length / 2 - behind, 0.0, 1.3))

    def path(times: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        positions = np.stack(
            [speed * times, -0.2 + _wave(times, 0.2, 11.0), 1.45 + _wave(times, 0.05, 7.0)], axis=-1
        )
        yaw = 0.55 + _wave(times, 0.2, 13.0)  # about 30 degrees towards the +y wall
        pitch = -0.1 + _wave(times, 0.06, 8.0)
        return positions, direction(yaw, pitch)

    return b.scene(seed), path, np.ones(frames)


def floor(
    rng: np.random.Generator, seed: int, frames: int
) -> tuple[Scene, PathFunction, np.ndarray]:
    """Wandering 1.1 m above a large tiled floor, looking 65 degrees down: only floor in view."""
    b = _Builder(rng)
    b.add(Rectangle(placed(0.0, 0.0, 0.0), (8.0, 8.0)), "floor")

    def path(times: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        positions = np.stack(
            [_wave(times, 0.9, 18.0), _wave(times, 0.6, 13.0, 0.5), 1.1 + _wave(times, 0.08, 8.0)],
            axis=-1,
        )
        yaw = 0.3 + _wave(times, 0.5, 25.0)
        pitch = np.radians(-65.0) + _wave(times, np.radians(5.0), 9.0)
        return positions, direction(yaw, pitch)

    return b.scene(seed), path, np.ones(frames)


def _wall_objects(b: _Builder, half_x: float, half_y: float) -> None:
    """Cabinets, pillars, stacks and posters along the four walls of a room centred at 0."""
    rng = b.rng
    walls = (  # (start corner, direction along the wall, inward normal, length)
        (np.array([-half_x, -half_y]), np.array([1.0, 0.0]), np.array([0.0, 1.0]), 2 * half_x),
        (np.array([half_x, -half_y]), np.array([0.0, 1.0]), np.array([-1.0, 0.0]), 2 * half_y),
        (np.array([half_x, half_y]), np.array([-1.0, 0.0]), np.array([0.0, -1.0]), 2 * half_x),
        (np.array([-half_x, half_y]), np.array([0.0, -1.0]), np.array([1.0, 0.0]), 2 * half_y),
    )
    for corner, along, inward, length in walls:
        yaw = np.degrees(np.arctan2(along[1], along[0]))
        s = 0.6
        while s < length - 0.6:
            kind = rng.choice(["cabinet", "pillar", "stack", "poster"])
            width = rng.uniform(0.4, 1.0)
            centre = corner + along * (s + width / 2)
            if kind == "cabinet":
                depth, height = rng.uniform(0.25, 0.5), rng.uniform(0.5, 1.8)
                xy = centre + inward * (depth / 2 + 0.01)
                b.add(
                    Box(placed(*xy, height / 2, yaw), (width / 2, depth / 2, height / 2)),
                    rng.choice(["wood", "object"]),
                )
            elif kind == "pillar":
                radius, height = min(width / 2, 0.3), rng.uniform(0.8, 2.6)
                xy = centre + inward * (radius + 0.05)
                b.add(Cylinder(placed(*xy, height / 2), radius, height / 2))
            elif kind == "stack":
                size = width / 2
                xy = centre + inward * (size + 0.02)
                b.add(Box(placed(*xy, size, yaw + rng.uniform(-15, 15)), (size, size, size)))
                b.add(Sphere(placed(*xy, 2 * size + 0.6 * size), 0.6 * size))
            else:  # a poster 5 mm in front of the wall, facing into the room
                height = rng.uniform(0.4, 0.9)
                xy = centre + inward * 0.005
                pose = placed(*xy, rng.uniform(1.0, 1.8), yaw)
                pose[:3, :3] = pose[:3, :3] @ np.array([[1.0, 0, 0], [0, 0, 1.0], [0, -1.0, 0]])
                b.add(Rectangle(pose, (width / 2, height / 2)))
            s += width + rng.uniform(0.2, 0.6)


def loop(
    rng: np.random.Generator, seed: int, frames: int
) -> tuple[Scene, PathFunction, np.ndarray]:
    """A 12 m lap (28 s) inside a 10 x 8 m room, looking out at objects along the walls."""
    b = _Builder(rng)
    b.room((5.0, 4.0, 1.5), (0.0, 0.0, 1.5))
    _wall_objects(b, 5.0, 4.0)

    def path(times: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        angle = 2 * np.pi * times / LOOP_LAP_SECONDS
        positions = np.stack(
            [2.3 * np.cos(angle), 1.55 * np.sin(angle), 1.4 + _wave(times, 0.06, 7.0)], axis=-1
        )
        yaw = angle + _wave(times, 0.25, 9.0)
        pitch = -0.2 + _wave(times, 0.05, 6.0)
        return positions, direction(yaw, pitch)

    return b.scene(seed), path, np.ones(frames)


@dataclass(frozen=True)
class ScenarioSpec:
    summary: str
    build: Callable[[np.random.Generator, int, int], tuple[Scene, PathFunction, np.ndarray]]


SCENARIOS = {
    "desk": ScenarioSpec(
        "a room with a table, objects and furniture; the camera sweeps around the table", desk
    ),
    "corridor": ScenarioSpec(
        "walking along a corridor of flat textured walls (ICP slides along it, paper Fig. 6)",
        corridor,
    ),
    "dark": ScenarioSpec("the furnished room; the light goes out (2%) for frames N/3..2N/3", dark),
    "floor": ScenarioSpec(
        "the camera sees only a textured floor (ICP is unconstrained, paper Fig. 7)", floor
    ),
    "loop": ScenarioSpec(
        "a 12 m closed lap in a 10 x 8 m room, objects along the walls (840 frames per lap)",
        loop,
    ),
}
