"""The cpu and cuda backends: kintinuous_ref.backend.Backend over this package's stage modules.

Every stage has one package here with the same layout (docs/architecture.md): `ops.py` holds its
per-element maths once, `cpu.py` the numba loops around it and `cuda.py` the numba.cuda
kernels, so a backend's stage module is `kintinuous_fast.<stage>.<backend>`. The two factories
below are the entry points pyproject.toml registers in the `kintinuous.backends` group.
"""

from __future__ import annotations

import importlib
import os
from types import ModuleType
from typing import Any

import numpy as np

from kintinuous_ref.backend import Backend, BackendUnavailable, DeviceTraffic
from kintinuous_ref.camera import Intrinsics
from kintinuous_ref.raycast import ModelPrediction
from kintinuous_ref.tsdf import TsdfVolume

STAGES = ("preprocess", "tsdf", "raycast", "colour", "odometry", "mesh")


class FastBackend:
    """The stages of one target ("cpu" or "cuda"), imported on first use."""

    def __init__(self, name: str, note: str = "") -> None:
        self.name = name
        self.note = note
        self._modules: dict[str, ModuleType] = {}

    def __getattr__(self, stage: str) -> ModuleType:
        if stage.startswith("_") or stage not in STAGES:
            raise AttributeError(stage)
        if stage not in self._modules:
            self._modules[stage] = importlib.import_module(f"kintinuous_fast.{stage}.{self.name}")
        return self._modules[stage]

    def upload(self, array: np.ndarray) -> Any:
        if self.name != "cuda":
            return array
        from kintinuous_fast.targets.cuda import upload_image

        return upload_image(array)

    def predict_surface(
        self, volume: Any, pose: np.ndarray, camera: Intrinsics, stride: int = 1
    ) -> ModelPrediction:
        # cuda's maps stay in device memory, where the next ICP reads them
        return self.raycast.predict_surface(volume, pose, camera, stride=stride)

    def volume_view(self, volume: Any) -> TsdfVolume:
        from kintinuous_fast.tsdf.volume import slab_view

        return slab_view(volume)

    def host_volume(self, volume: Any) -> TsdfVolume:
        from kintinuous_fast.tsdf.volume import to_reference_volume

        return to_reference_volume(volume)

    def device_traffic(self) -> DeviceTraffic:
        """For cuda: the kernel launches, host waits and downloaded bytes so far
        (targets.TRAFFIC); for cpu, which has no device, zeros."""
        if self.name != "cuda":
            return DeviceTraffic()
        from kintinuous_fast.targets import TRAFFIC

        return DeviceTraffic(
            TRAFFIC.launches, TRAFFIC.host_waits, TRAFFIC.bytes_to_host, TRAFFIC.graph_replays
        )

    def synchronize(self) -> None:
        """For cuda: run the recorded launches and wait for the device; cpu's loops return
        when done."""
        if self.name != "cuda":
            return
        from numba import cuda

        from kintinuous_fast.targets import cuda_graphs

        cuda_graphs.flush()
        cuda.synchronize()

    def kernels_cached(self, tracking: bool = True) -> bool:
        """For cpu: whether a warm-up from these sources recorded the kernels of each stage a
        run calls (with `tracking`, all five; without, preprocessing, integration and colour)
        in numba's on-disk cache (targets/cache.py). The cuda kernels are compiled at their
        first launch in the process that launches them, so there is nothing to compile ahead
        elsewhere: True."""
        if self.name != "cpu":
            return True
        from kintinuous_fast.targets import cache

        return cache.warmed_up(cache.STAGES if tracking else cache.MAPPING_STAGES)

    def record_warm_up(self, tracking: bool = True) -> None:
        """For cpu: record, beside the cached kernels, that a warm-up compiled those of each
        stage a run calls (kernels_cached reads it)."""
        if self.name != "cpu":
            return
        from kintinuous_fast.targets import cache

        cache.record_warm_up(cache.STAGES if tracking else cache.MAPPING_STAGES)

    def compile_seconds(self, part: str) -> float | None:
        """For cpu: the compile time of `part` last measured into numba's on-disk cache here
        (targets/cache.py); None for cuda, whose kernels compile in every process."""
        if self.name != "cpu":
            return None
        from kintinuous_fast.targets import cache

        return cache.measured_compile_seconds(part)

    def record_compile_seconds(self, part: str, seconds: float) -> None:
        """For cpu: keep `seconds` beside the cached kernels for compile_seconds."""
        if self.name != "cpu":
            return
        from kintinuous_fast.targets import cache

        cache.record_compile_seconds(part, seconds)

    def __repr__(self) -> str:
        return f"FastBackend({self.name!r})"


def numba_status() -> str:
    """'' when numba imports here, else why not."""
    try:
        import numba  # noqa: F401
    except ImportError as err:
        return f"numba cannot be imported ({err})"
    return ""


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


def cpu_backend() -> Backend:
    """The cpu backend (entry point "cpu"): numba parallel loops, cached on disk."""
    reason = numba_status()
    if reason:
        raise BackendUnavailable(f"backend 'cpu' does not work on this machine: {reason}")
    from kintinuous_fast.targets.cache import drop_stale_kernels
    from kintinuous_fast.targets.cpu import threading_note
    from kintinuous_fast.targets.host_memory import hold_freed_memory

    drop_stale_kernels()  # kernels cached from other sources (targets/cache.py)
    hold_freed_memory()  # a frame's freed arrays serve the next one (targets/host_memory.py)
    return FastBackend("cpu", threading_note())


def cuda_backend() -> Backend:
    """The cuda backend (entry point "cuda"): numba.cuda kernels, arrays kept on the device."""
    reason = numba_status() or cuda_status()
    if reason:
        raise BackendUnavailable(f"backend 'cuda' does not work on this machine: {reason}")
    from kintinuous_fast.targets import cuda_graphs

    notes = [
        "numba's CUDA simulator (NUMBA_ENABLE_CUDASIM=1), very slow" if cuda_is_simulated() else "",
        f"repeating launches replayed as CUDA graphs ({cuda_graphs.ENVIRONMENT}=1)"
        if cuda_graphs.enabled()
        else "",
    ]
    return FastBackend("cuda", "; ".join(note for note in notes if note))
