"""Synthetic RGB-D sequences with exact ground truth: scenes of simple solids, ray cast.

    scenario = make_scenario("corridor", frames=90, width=160, height=120, noise=False)
    colour, depth = scenario.render(10)          # (H, W, 3) uint8 RGB, (H, W) float32 m, 0 = none
    scenario.trajectory.poses[10]                # its exact camera-to-world pose
    write_scenario("desk", "out/desk")           # a TUM folder + scene.ply

Modules: solids (closed-form ray intersections), textures (procedural multi-scale textures),
scene (ray casting and shading), sensor (the Kinect error model), trajectories (hand-held paths),
scenarios (the five layouts), revisits (loop closure: a drifting lap, perceptual aliasing).
"""

from __future__ import annotations

import json
import os
import shutil
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from kintinuous_ref import se3
from kintinuous_ref.camera import Intrinsics
from kintinuous_ref.datasets.synthetic.revisits import REVISITS
from kintinuous_ref.datasets.synthetic.scenarios import SCENARIOS as _LAYOUTS
from kintinuous_ref.datasets.synthetic.scene import Scene, rotate
from kintinuous_ref.datasets.synthetic.sensor import SensorModel, measure_colour, measure_depth
from kintinuous_ref.datasets.synthetic.trajectories import FRAME_RATE, START_TIME, hand_held
from kintinuous_ref.datasets.tum import Trajectory, write_file, write_image, write_trajectory
from kintinuous_ref.errors import ConfigError, DatasetError
from kintinuous_ref.strict_json import dumps as strict_dumps

if TYPE_CHECKING:
    import pyvista

# The five layouts of the paper's experiments, and the loop-closure scenarios (revisits.py).
SCENARIOS = {**_LAYOUTS, **REVISITS}

__all__ = [
    "KINECT_CAMERA",
    "Scenario",
    "SensorModel",
    "list_scenarios",
    "make_scenario",
    "write_scenario",
]

# The usual nominal Kinect v1 calibration at 640 x 480; other sizes scale it (Intrinsics.resized).
KINECT_CAMERA = Intrinsics(525.0, 525.0, 319.5, 239.5, 640, 480)


def list_scenarios() -> dict[str, str]:
    """Scenario name -> one-line summary."""
    return {name: spec.summary for name, spec in SCENARIOS.items()}


class Scenario:
    """A scene, a camera, a ground-truth trajectory at 30 Hz and a sensor model."""

    def __init__(
        self,
        name: str,
        scene: Scene,
        camera: Intrinsics,
        trajectory: Trajectory,
        brightness: np.ndarray,
        sensor: SensorModel,
        seed: int = 0,
    ) -> None:
        self.name = name
        self.scene = scene
        self.camera = camera
        self.trajectory = trajectory
        self.brightness = brightness  # (frames,) light level per frame, 1 = normal
        self.sensor = sensor
        self.seed = seed

    def __len__(self) -> int:
        return len(self.trajectory)

    @property
    def noise(self) -> bool:
        return self.sensor != SensorModel.exact()

    def render(self, index: int) -> tuple[np.ndarray, np.ndarray]:
        """Frame `index`: (colour (H, W, 3) uint8 RGB, depth (H, W) float32 metres, 0 = none)."""
        if not 0 <= index < len(self):
            raise DatasetError(f"scenario '{self.name}' has frames 0..{len(self) - 1}, not {index}")
        rng = np.random.default_rng([self.seed, 1, index])
        return self._render(self.trajectory.poses[index], self.sensor, self.brightness[index], rng)

    def render_at(
        self, pose: np.ndarray, noise: bool | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        """The scene seen from any camera-to-world `pose` under normal light.

        noise None: the scenario's own sensor; False: exact; True: the Kinect-like sensor.
        """
        pose = np.asarray(pose, dtype=np.float64)
        se3.check_pose(pose)
        sensor = self.sensor if noise is None else (SensorModel() if noise else SensorModel.exact())
        # noise depends only on the seed and the pose, so the same call gives the same image
        entropy = np.frombuffer(np.ascontiguousarray(pose).tobytes(), dtype=np.uint32)
        rng = np.random.default_rng([self.seed, 2, *entropy.tolist()])
        return self._render(pose, sensor, 1.0, rng)

    def _render(
        self, pose: np.ndarray, sensor: SensorModel, brightness: float, rng: np.random.Generator
    ) -> tuple[np.ndarray, np.ndarray]:
        hits = self.scene.raycast(self.camera, pose)
        # metres per pixel on the surface (for texture anti-aliasing): z / f, stretched when oblique
        focal = 0.5 * (self.camera.fx + self.camera.fy)
        cos_incidence = hits.cos_incidence.ravel()[hits.pixels]
        footprint = hits.depth.ravel()[hits.pixels] / (focal * np.maximum(cos_incidence, 0.25))
        colour = self.scene.shade(hits, footprint)
        depth = measure_depth(
            hits.depth, hits.cos_incidence, sensor, self.camera.depth_scale, rng, focal
        )
        return measure_colour(colour, brightness, sensor, rng), depth

    def surface_mesh(self, spacing: float = 0.05) -> pyvista.PolyData:
        """The ground-truth surface: a coloured triangle mesh in world coordinates.

        Point array "rgb" (uint8) holds each vertex's colour under normal light; triangle edges
        are at most about `spacing` metres. (Saved as PLY with texture="rgb" and read back,
        pyvista names the array "RGB".)
        """
        import pyvista

        if not 0.001 <= spacing <= 10.0:
            raise ConfigError(f"mesh spacing must be within 0.001..10 m, got {spacing}")
        points, triangles, colours = [], [], []
        offset = 0
        for index, solid in enumerate(self.scene.solids):
            part = solid.mesh(spacing)
            world = rotate(part.points, solid.pose[:3, :3]) + solid.pose[:3, 3]
            normals = rotate(part.normals, solid.pose[:3, :3])
            surface = self.scene.surface_offsets[index] + part.face
            colours.append(self.scene.colour_at(surface, part.uv, normals, spacing))
            points.append(world)
            triangles.append(part.triangles + offset)
            offset += len(world)
        triangles = np.concatenate(triangles)
        cells = np.column_stack([np.full(len(triangles), 3), triangles]).ravel()
        mesh = pyvista.PolyData(np.concatenate(points), cells)
        rgb = np.clip(np.round(np.concatenate(colours) * 255.0), 0, 255).astype(np.uint8)
        mesh.point_data["rgb"] = rgb
        return mesh


def make_scenario(
    name: str,
    frames: int = 300,
    width: int = 640,
    height: int = 480,
    seed: int = 0,
    noise: bool = True,
) -> Scenario:
    """Build scenario `name` (see list_scenarios) with `frames` poses at 30 Hz; renders lazily."""
    if name not in SCENARIOS:
        raise ConfigError(f"unknown scenario '{name}'; choose one of {', '.join(SCENARIOS)}")
    if frames < 1:
        raise ConfigError(f"frames must be at least 1, got {frames}")
    if seed < 0:
        raise ConfigError(f"seed must be >= 0, got {seed}")
    if width < 8 or height < 8:
        raise ConfigError(f"image size must be at least 8x8, got {width}x{height}")
    rng = np.random.default_rng([seed, 0])
    scene, path, brightness = SCENARIOS[name].build(rng, seed, frames)
    poses = hand_held(path, frames, np.random.default_rng([seed, 3]))
    timestamps = START_TIME + np.arange(frames) / FRAME_RATE
    camera = (
        KINECT_CAMERA.resized(width, height) if (width, height) != (640, 480) else KINECT_CAMERA
    )
    sensor = SensorModel() if noise else SensorModel.exact()
    return Scenario(name, scene, camera, Trajectory(timestamps, poses), brightness, sensor, seed)


def _prepare_folder(out: Path, meta: dict) -> bool:
    """Create `out`, or reuse it if empty or an earlier synth output. True when it holds frames
    of the same scenario (`meta` equal), which are kept; an other scenario's frames are removed."""
    if out.exists() and not out.is_dir():
        raise DatasetError(f"{out}: exists and is not a folder")
    same = False
    if out.is_dir() and any(not p.name.startswith(".") for p in out.iterdir()):  # not a lock
        if not (out / "scenario.json").is_file():
            raise DatasetError(f"{out}: folder is not empty and not an earlier synth output")
        try:
            same = json.loads((out / "scenario.json").read_text()) == meta
        except (OSError, ValueError):
            same = False
        if not same:
            for sub in ("rgb", "depth"):
                shutil.rmtree(out / sub, ignore_errors=True)
    (out / "rgb").mkdir(parents=True, exist_ok=True)
    (out / "depth").mkdir(parents=True, exist_ok=True)
    return same


def _write_frames(
    out: Path, names: list[str], indices: list[int], build: tuple, scenario: Scenario | None = None
) -> int:
    """Render and write frames `indices` (in a worker process: builds its own scenario)."""
    import cv2

    scenario = scenario or make_scenario(*build)
    # small sequences end up in repositories as fixtures: smallest files (zlib level 9 costs
    # ~25 ms per 160x120 image); large ones are written fast (level 1, 4-20x quicker)
    small = scenario.camera.width * scenario.camera.height <= 320 * 240
    options = [cv2.IMWRITE_PNG_COMPRESSION, 9 if small else 1]
    for index in indices:
        colour, depth = scenario.render(index)
        units = np.round(depth.astype(np.float64) * scenario.camera.depth_scale)
        units[units > np.iinfo(np.uint16).max] = 0  # beyond what uint16 holds: no measurement
        for path, image in (
            (out / "rgb" / names[index], colour[..., ::-1]),  # OpenCV writes BGR
            (out / "depth" / names[index], units.astype(np.uint16)),
        ):
            _write_whole(path, image, options)
    return len(indices)


def _write_whole(path: Path, image: np.ndarray, options: list[int]) -> None:
    """`image` written under a temporary name and renamed: a render stopped during the write
    (Ctrl-C) leaves no half image that a later render would take for a written frame."""
    partial = path.with_name(f".{path.stem}.partial{path.suffix}")
    try:
        write_image(partial, image, options)
    except DatasetError as err:  # named as the image the user asked for
        partial.unlink(missing_ok=True)
        raise DatasetError(str(err).replace(str(partial), str(path), 1)) from None
    os.replace(partial, path)


def write_scenario(
    name: str,
    out: Path | str,
    frames: int = 300,
    width: int = 640,
    height: int = 480,
    seed: int = 0,
    noise: bool = True,
    progress: bool = False,
    workers: int = 1,
    mesh_spacing: float = 0.05,
    render: int | None = None,
    on_rendering: Callable[[int], None] | None = None,
) -> Path:
    """Render a scenario into a TUM-layout folder; returns the folder.

    `render` N renders only the first N of the scenario's `frames` (the listings name those;
    groundtruth.txt holds every pose): the same images as a full render, since the scenario
    (its path, lighting, noise) is built for `frames`. Rendering again into the same folder with
    a larger N keeps the frames already there and adds the rest.

    Writes rgb/*.png (8-bit colour), depth/*.png (uint16, 1/5000 m, 0 = none), rgb.txt, depth.txt,
    associations.txt, groundtruth.txt (camera-to-world, TUM format), intrinsics.json,
    scene.ply (ground-truth surface, binary PLY with per-vertex RGB) and scenario.json.
    workers > 1 renders frames in that many processes; mesh_spacing: the mesh's edge length (m).
    `on_rendering`, once the folder is complete, is given how many frames this call rendered
    (0 when the folder held them all).
    """
    if workers < 1:
        raise ConfigError(f"workers must be at least 1, got {workers}")
    if frames < 1:  # before the render range, which it bounds
        raise ConfigError(f"frames must be at least 1, got {frames}")
    build = (name, frames, width, height, seed, noise)
    rendered = frames if render is None else render
    if not 1 <= rendered <= frames:
        raise ConfigError(f"can render 1..{frames} frames of '{name}', asked for {rendered}")
    scenario = make_scenario(*build)
    out = Path(out)
    dark = np.flatnonzero(scenario.brightness < 1.0)
    meta = {
        "scenario": name,
        "summary": SCENARIOS[name].summary,
        "frames": frames,
        "width": scenario.camera.width,
        "height": scenario.camera.height,
        "seed": seed,
        "noise": noise,
        "frame_rate": FRAME_RATE,
        "dark_frames": [int(dark[0]), int(dark[-1])] if len(dark) else None,
        "sensor": dict(vars(scenario.sensor)),
    }
    meta = json.loads(strict_dumps(meta))  # as it reads back from scenario.json
    same = _prepare_folder(out, meta)
    # first, so that an interrupted run's folder is recognised (and reused) as ours
    write_file(out / "scenario.json", strict_dumps(meta, indent=2) + "\n")
    timestamps = scenario.trajectory.timestamps
    names = [f"{t:.6f}.png" for t in timestamps]

    def written(index: int) -> bool:
        return same and all((out / kind / names[index]).is_file() for kind in ("rgb", "depth"))

    missing = [index for index in range(rendered) if not written(index)]
    chunk = 10
    chunks = [missing[i : i + chunk] for i in range(0, len(missing), chunk)]
    from tqdm import tqdm

    # closed however rendering ends, so that an error is printed on a line of its own
    with tqdm(total=len(missing), desc=f"synth {name}", unit="frame", disable=not progress) as bar:
        if workers > 1 and len(chunks) > 1:
            from concurrent.futures import ProcessPoolExecutor, as_completed

            with ProcessPoolExecutor(max_workers=workers) as pool:
                futures = [pool.submit(_write_frames, out, names, c, build) for c in chunks]
                for future in as_completed(futures):
                    bar.update(future.result())
        else:
            for c in chunks:
                bar.update(_write_frames(out, names, c, build, scenario))

    def listing(kind: str) -> str:
        lines = [f"# {kind} images of synthetic scenario '{name}'", "# timestamp filename"]
        lines += [f"{t:.6f} {kind}/{n}" for t, n in zip(timestamps[:rendered], names, strict=False)]
        return "\n".join(lines) + "\n"

    # before the listings, so that associations.txt is written last: a folder that lists its
    # frames holds its surface too (a render stopped while the mesh is made lists none)
    if not (same and (out / "scene.ply").is_file()):
        _write_surface(scenario, out / "scene.ply", mesh_spacing)
    write_file(out / "rgb.txt", listing("rgb").replace("# rgb images", "# color images"))
    write_file(out / "depth.txt", listing("depth"))
    pairs = [
        f"{t:.6f} rgb/{n} {t:.6f} depth/{n}"
        for t, n in zip(timestamps[:rendered], names, strict=False)
    ]
    write_file(out / "associations.txt", "\n".join(pairs) + "\n")
    write_trajectory(out / "groundtruth.txt", scenario.trajectory)
    write_file(out / "intrinsics.json", strict_dumps(scenario.camera.to_json(), indent=2) + "\n")
    if on_rendering is not None:
        on_rendering(len(missing))
    return out


def _write_surface(scenario: Scenario, path: Path, mesh_spacing: float) -> None:
    """The scenario's true surface as a binary PLY, written under a temporary name and
    renamed, so that a stopped write leaves no partial scene.ply."""
    partial = path.with_name(f".{path.stem}.partial{path.suffix}")
    mesh = scenario.surface_mesh(mesh_spacing)
    try:
        mesh.save(str(partial), binary=True, texture="rgb")
        os.replace(partial, path)
    except OSError as err:
        partial.unlink(missing_ok=True)
        raise DatasetError(f"{path}: cannot write ({err.strerror or err})") from None
