"""kintinuous_fast: the functions of kintinuous_ref with the same names and signatures, compiled
with numba: CUDA kernels where a GPU is present, parallel CPU loops (`prange`) where not.

Three interchangeable backends, each a set of modules with kintinuous_ref's public names:

- "ref":  kintinuous_ref itself (NumPy, the specification),
- "cpu":  kintinuous_fast.cpu (numba.njit, parallel, cached),
- "cuda": kintinuous_fast.cuda (numba.cuda kernels; arrays stay where they are given: device
          arrays in, device arrays out, so a pipeline can keep its state in GPU memory),
- "auto": "cuda" when a GPU (or numba's simulator) works here, else "cpu".

A pipeline keeps its state where the backend computes: `backend.upload(image)` puts a frame's
images there once (device memory for cuda, unchanged for cpu / ref), every stage then takes and
returns arrays in that place, and `backend.predict_surface` leaves the raycast maps there for the
next frame's tracking.

The per-element maths (filter one pixel, update one voxel, ...) lives once, in kintinuous_fast.ops,
and is compiled for both targets; only the loops (cpu) and the launches (cuda) differ.

    backend = select_backend("auto")
    frame = backend.preprocess.preprocess_frame(colour, depth, camera, config.preprocess)

`kintinuous_fast.preprocess` (and the other top-level modules) are the "auto" backend's modules.
"""

from __future__ import annotations

import importlib
import os
from dataclasses import dataclass, field
from types import ModuleType
from typing import Any

from kintinuous_ref.errors import ConfigError

BACKENDS = ("ref", "cpu", "cuda", "auto")
# The stages each backend provides (module names shared with kintinuous_ref).
STAGES = ("preprocess", "colour", "tsdf", "raycast", "odometry")
_PACKAGES = {"ref": "kintinuous_ref", "cpu": "kintinuous_fast.cpu", "cuda": "kintinuous_fast.cuda"}
# Stages whose modules live elsewhere than {package}.{stage}: the fast trackers (each module has
# make_tracker(method, config, camera) with kintinuous_ref.odometry's signature).
_MODULES = {
    ("cpu", "odometry"): "kintinuous_fast.odometry.cpu",
    ("cuda", "odometry"): "kintinuous_fast.odometry.cuda",
}


@dataclass
class Backend:
    """One backend's modules, looked up by stage name: backend.preprocess, backend.tsdf, ..."""

    name: str  # "ref", "cpu" or "cuda" (never "auto": that resolves to one of them)
    _modules: dict[str, ModuleType] = field(default_factory=dict, repr=False)

    def __getattr__(self, stage: str) -> ModuleType:
        if stage.startswith("_") or stage not in STAGES:
            raise AttributeError(stage)
        if stage not in self._modules:
            try:
                module = _MODULES.get((self.name, stage), f"{_PACKAGES[self.name]}.{stage}")
                self._modules[stage] = importlib.import_module(module)
            except ModuleNotFoundError as err:
                raise ConfigError(
                    f"backend {self.name!r} has no {stage} stage yet ({err.name} missing)"
                ) from None
        return self._modules[stage]

    def upload(self, array: Any) -> Any:
        """`array` where this backend computes: a device array for cuda (one copy per call),
        the array itself for cpu and ref."""
        if self.name != "cuda":
            return array
        from kintinuous_fast.cuda import to_device

        return to_device(array)

    def predict_surface(self, volume: Any, pose: Any, camera: Any, stride: int = 1) -> Any:
        """The pipeline's model prediction (kintinuous_ref.pipeline.predict_surface), with the
        maps left where they were computed (device memory for cuda: the next frame's ICP reads
        them there)."""
        if self.name == "cuda":
            return self.raycast.raycast(
                volume, pose, camera, colour=False, stride=stride, download=False
            )
        return self.raycast.raycast(volume, pose, camera, colour=False, stride=stride)


def cuda_status() -> str:
    """'' when numba's CUDA target works here (a GPU, or the simulator), else why not."""
    try:
        from numba import cuda
    except ImportError as err:  # numba builds without the CUDA target
        return f"numba.cuda cannot be imported ({err})"
    try:
        if cuda.is_available():
            return ""
        return "no CUDA GPU or driver found"
    except Exception as err:  # a broken driver install: report, never crash the caller
        return f"CUDA driver error: {err}"


def cuda_is_simulated() -> bool:
    """True when numba's CUDA simulator stands in for a GPU (NUMBA_ENABLE_CUDASIM=1)."""
    return os.environ.get("NUMBA_ENABLE_CUDASIM", "0") == "1"


def backend_status() -> dict[str, str]:
    """Every backend name -> '' when it works on this machine, else the reason it does not."""
    status = {"ref": "", "cpu": ""}
    try:
        import numba  # noqa: F401
    except ImportError as err:
        status["cpu"] = f"numba cannot be imported ({err})"
    status["cuda"] = cuda_status()
    return status


def available_backends() -> list[str]:
    """The backends that work on this machine, fastest first (auto picks the first of cuda/cpu)."""
    status = backend_status()
    return [name for name in ("cuda", "cpu", "ref") if not status[name]]


def resolve_backend_name(name: str) -> str:
    """'auto' -> 'cuda' or 'cpu'; other names are checked and returned unchanged."""
    if name not in BACKENDS:
        raise ConfigError(f"unknown backend {name!r}; choose one of {', '.join(BACKENDS)}")
    if name == "auto":
        return "cuda" if not cuda_status() else "cpu"
    reason = backend_status()[name]
    if reason:
        raise ConfigError(f"backend {name!r} does not work on this machine: {reason}")
    return name


_SELECTED: dict[str, Backend] = {}


def select_backend(name: str = "auto") -> Backend:
    """The backend called `name` (ref, cpu, cuda or auto); ConfigError if it cannot run here."""
    resolved = resolve_backend_name(name)
    if resolved not in _SELECTED:
        _SELECTED[resolved] = Backend(resolved)
    return _SELECTED[resolved]
