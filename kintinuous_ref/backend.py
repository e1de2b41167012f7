"""What the pipeline needs from a backend, written down: the `Backend` protocol, the reference's
own implementation of it, and how the other backends are found.

A backend computes the five stages of a frame (docs/architecture.md). Each stage is a module
with kintinuous_ref's public names and signatures for that stage:

    preprocess   preprocess_frame(colour, depth, camera, config) -> PreprocessedFrame
    tsdf         check_volume_config(config), make_volume(config, pose, max_colour_weight),
                 integrate(volume, depth, pose, camera, colour, colour_weights)
    raycast      raycast(volume, pose, camera, skip_empty=True, colour=True, stride=1),
                 predict_surface(volume, pose, camera, stride=1) -> ModelPrediction
    colour       colour_weights(frame, config) -> weights per pixel
    odometry     make_tracker(method, config, camera) -> Tracker

Beside the stages a backend says where its arrays live (`upload`, `predict_surface`) and how its
volume is seen as a reference TsdfVolume (`volume_view` for the moving volume's slices, sharing
memory; `host_volume` for meshing, a copy on the host).

kintinuous_ref is the specification and stands alone: it never imports the fast backends.
They plug in through Python's plugin convention, the entry-point group `kintinuous.backends`:
each entry point names a function that returns a Backend, or raises BackendUnavailable with the
reason it cannot run on this machine. kintinuous_fast registers "cpu" and "cuda" in
pyproject.toml; "auto" picks the first of cuda and cpu that runs here, else the reference.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from importlib.metadata import EntryPoint, entry_points
from types import ModuleType
from typing import Any, Protocol, runtime_checkable

import numpy as np

from kintinuous_ref.camera import Intrinsics
from kintinuous_ref.errors import ConfigError
from kintinuous_ref.raycast import ModelPrediction
from kintinuous_ref.tsdf import TsdfVolume
from kintinuous_ref.vocabulary import BACKENDS

ENTRY_POINT_GROUP = "kintinuous.backends"
REFERENCE = "ref"
AUTO = "auto"
# The order "auto" tries the plugged-in backends in: the fastest first.
AUTO_ORDER = ("cuda", "cpu")
# The backends the project itself ships (kintinuous_fast's are named even when not installed,
# so `kintinuous info` can say why they are missing).
KNOWN = BACKENDS


@dataclass(frozen=True)
class DeviceTraffic:
    """What the host has asked of an accelerator so far: kernel launches, blocking downloads
    (each one a wait for every kernel before it), the bytes they brought back, and how many
    recorded sequences of launches were replayed as one graph launch each (of the launches,
    those replayed cost the host no dispatch of their own). A backend that computes where its
    caller runs (the reference, cpu) has none: all zeros."""

    launches: int = 0
    host_waits: int = 0
    bytes_to_host: int = 0
    graph_replays: int = 0

    def __sub__(self, earlier: DeviceTraffic) -> DeviceTraffic:
        return DeviceTraffic(
            self.launches - earlier.launches,
            self.host_waits - earlier.host_waits,
            self.bytes_to_host - earlier.bytes_to_host,
            self.graph_replays - earlier.graph_replays,
        )


class BackendUnavailable(ConfigError):
    """A backend that exists but cannot run on this machine (no GPU, no numba, ...)."""


@runtime_checkable
class Backend(Protocol):
    """One way of computing the pipeline's stages (see the module docstring)."""

    name: str
    note: str  # one line about how it runs here ("" or, e.g., "numba's CUDA simulator")
    preprocess: ModuleType
    tsdf: ModuleType
    raycast: ModuleType
    colour: ModuleType
    odometry: ModuleType
    mesh: ModuleType  # marching_cubes(tsdf, weight, min_weight), kintinuous_ref.marching_cubes's

    def upload(self, array: np.ndarray) -> Any:
        """`array` where this backend computes (device memory, or the array itself)."""
        ...

    def predict_surface(
        self, volume: Any, pose: np.ndarray, camera: Intrinsics, stride: int = 1
    ) -> ModelPrediction:
        """The model prediction for the next frame's tracking, left where it was computed."""
        ...

    def volume_view(self, volume: Any) -> TsdfVolume:
        """`volume` as a TsdfVolume sharing its cells (the moving volume shifts and clears it)."""
        ...

    def host_volume(self, volume: Any) -> TsdfVolume:
        """`volume` as a host TsdfVolume for meshing and output."""
        ...

    def device_traffic(self) -> DeviceTraffic:
        """The launches, host waits and downloaded bytes counted since the process started
        (zeros for a backend without an accelerator)."""
        ...

    def synchronize(self) -> None:
        """Return once the work queued on an accelerator so far is done (at once without one):
        what a stage's time must wait for to include its device work."""
        ...

    def kernels_cached(self, tracking: bool = True) -> bool:
        """False when a run (with `tracking`, one that tracks and raycasts; without, one that
        maps with known poses) would first compile kernels that other processes could compile
        into an on-disk cache for it (kintinuous_ref.program.warmup); True otherwise."""
        ...

    def record_warm_up(self, tracking: bool = True) -> None:
        """Called by the warm-up once a run (with or without `tracking`) has compiled every
        kernel it calls: from then on kernels_cached says so, in other processes too."""
        ...

    def compile_seconds(self, part: str) -> float | None:
        """How long compiling `part` of the kernels (kintinuous_ref.program.warmup's
        COMPILE_PARTS) took when last measured on this machine; None where it never was."""
        ...

    def record_compile_seconds(self, part: str, seconds: float) -> None:
        """Keep a measured compile time of `part` for compile_seconds, in other processes too."""
        ...


class ReferenceBackend:
    """The reference implements the protocol with its own modules (NumPy on the host)."""

    name = REFERENCE
    note = ""

    def __init__(self) -> None:
        import kintinuous_ref.colour
        import kintinuous_ref.marching_cubes
        import kintinuous_ref.odometry
        import kintinuous_ref.preprocess
        import kintinuous_ref.raycast
        import kintinuous_ref.tsdf

        self.preprocess = kintinuous_ref.preprocess
        self.tsdf = kintinuous_ref.tsdf
        self.raycast = kintinuous_ref.raycast
        self.colour = kintinuous_ref.colour
        self.odometry = kintinuous_ref.odometry
        self.mesh = kintinuous_ref.marching_cubes

    def upload(self, array: np.ndarray) -> np.ndarray:
        return array

    def predict_surface(
        self, volume: TsdfVolume, pose: np.ndarray, camera: Intrinsics, stride: int = 1
    ) -> ModelPrediction:
        return self.raycast.predict_surface(volume, pose, camera, stride=stride)

    def volume_view(self, volume: TsdfVolume) -> TsdfVolume:
        return volume

    def host_volume(self, volume: TsdfVolume) -> TsdfVolume:
        return volume

    def device_traffic(self) -> DeviceTraffic:
        return DeviceTraffic()  # NumPy on the host: no device

    def synchronize(self) -> None:
        pass  # NumPy returns when its work is done

    def kernels_cached(self, tracking: bool = True) -> bool:
        return True  # NumPy: nothing to compile

    def record_warm_up(self, tracking: bool = True) -> None:
        return None

    def compile_seconds(self, part: str) -> float | None:
        return None  # NumPy: nothing is compiled

    def record_compile_seconds(self, part: str, seconds: float) -> None:
        return None

    def __repr__(self) -> str:
        return "ReferenceBackend()"


_LOADED: dict[str, Backend] = {}


def plugins() -> dict[str, EntryPoint]:
    """The installed backends other than the reference, by name (listing them imports nothing:
    an entry point is loaded only when its backend is asked for)."""
    return {point.name: point for point in entry_points(group=ENTRY_POINT_GROUP)}


def backend_names() -> tuple[str, ...]:
    """Every name `load_backend` accepts, installed or not."""
    return (*dict.fromkeys((*KNOWN, *plugins())), AUTO)


def _load_plugin(name: str) -> Backend:
    point = plugins().get(name)
    if point is None:
        raise BackendUnavailable(
            f"backend {name!r} is not installed (it comes with the kintinuous_fast package)"
        )
    try:
        make_backend: Callable[[], Backend] = point.load()
    except ImportError as err:
        raise BackendUnavailable(f"backend {name!r} cannot be imported: {err}") from None
    return make_backend()


def load_backend(name: str = AUTO) -> Backend:
    """The backend called `name`: "ref", an installed one ("cpu", "cuda"), or "auto" (the first
    of cuda and cpu that runs here, else the reference). ConfigError names the choices for an
    unknown name; BackendUnavailable says why a known one cannot run here."""
    if name not in backend_names():
        raise ConfigError(f"unknown backend {name!r}; choose one of {', '.join(backend_names())}")
    if name == AUTO:
        for candidate in AUTO_ORDER:
            try:
                return load_backend(candidate)
            except BackendUnavailable:
                continue
        return load_backend(REFERENCE)
    if name not in _LOADED:
        _LOADED[name] = ReferenceBackend() if name == REFERENCE else _load_plugin(name)
    return _LOADED[name]


def backend_status() -> dict[str, str]:
    """Every backend name (but "auto") -> "" when it runs on this machine, else why not."""
    status = {}
    for name in backend_names():
        if name == AUTO:
            continue
        try:
            load_backend(name)
            status[name] = ""
        except BackendUnavailable as err:
            status[name] = str(err)
    return status
