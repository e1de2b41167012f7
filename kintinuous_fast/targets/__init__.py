"""The targets: each one's decorators (here) and helpers (cpu.py: threads, prefetch; cuda.py:
device arrays, grids; cache.py: numba's on-disk cache), and the one download helper, to_host.

Per-element maths is written once and compiled for both targets. Each stage's ops module has a
factory `build_ops(jit)` that defines scalar functions (filter one pixel,
update one voxel, ...) with the decorator it is given and returns them in a namespace. The CPU
backend calls it with `numba.njit(cache=True)` and loops over pixels (targets/cpu.py); the CUDA
backend calls it with `cuda.jit(device=True)` and launches one thread per pixel. The functions
may call each other: they are closures over the factory's scope, compiled with the same target.

Arithmetic rule (so that all targets, numba's CUDA simulator included, round alike): values read
from arrays are converted with float() where the reference computes in float64, and with
np.float32() where the reference computes in float32, so no result depends on how a target
promotes mixed float32/float64 expressions.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numba
import numpy as np

from kintinuous_fast.targets import cuda_graphs

# The CPU decorator: compiled on first use and cached on disk (compile time counts in the tests).
cpu_jit: Callable[[Any], Any] = numba.njit(cache=True)
# The same with NumPy's error model: a float division by zero gives inf/NaN instead of a Python
# ZeroDivisionError, so numba emits no zero test and exception path per division (the per-voxel
# loops run several times as fast: docs/benchmarks.md, "Numbers behind the fast stages"). Only for
# code whose divisions are guarded (tsdf.voxel, tsdf.ops, raycast.ops: z > 0, b != 0, ...).
cpu_jit_numpy_errors: Callable[[Any], Any] = numba.njit(
    cache=True, error_model="numpy", inline="always"
)
# The same, called rather than inlined by numba (`jit_called` of tsdf.voxel and raycast.ops: LLVM
# still inlines the small ones, at a fraction of the compile time), and without numba's
# reference counting: these functions allocate nothing, but with it the array arguments of the
# functions inlined into their loops are counted up and down on every step of a ray, in
# branches that numba's pruning pass cannot pair up, each an atomic operation on a count that
# the other threads update too. Without them the raycast is 13-16 % faster, bit-identical
# (docs/benchmarks_archive_2026-11-21_24.md, 2026-11-22). A function compiled so that does need
# it fails to compile.
cpu_jit_numpy_errors_called: Callable[[Any], Any] = numba.njit(
    cache=True, error_model="numpy", _nrt=False
)


# 1.5 * 2^52 and 1.5 * 2^23: added to a float64 (float32) below 2^51 (2^22) in magnitude, they
# leave no fraction bits, so the sum is the value rounded half to even in the default rounding
# mode, and subtracting them again is exact.
_RINT_SHIFT = 6755399441055744.0
_RINT_SHIFT32 = np.float32(12582912.0)


def build_rint(jit: Callable[[Any], Any]) -> tuple[Callable[[Any], Any], Callable[[Any], Any]]:
    """(rint, rint32) compiled with `jit`: np.rint of a float64 and of a float32, in that
    precision, for the ops factories that round to pixels (odometry, volume). No branch, so the
    CPU's projection loops vectorise (rint32 16 lanes wide); np.rint has no CUDA lowering.
    Larger values than the bounds above come back within a few units (far outside any image);
    NaN and inf stay NaN and inf."""

    @jit
    def rint(x: float) -> float:
        return (x + _RINT_SHIFT) - _RINT_SHIFT

    @jit
    def rint32(x: Any) -> Any:
        return (x + _RINT_SHIFT32) - _RINT_SHIFT32

    return rint, rint32


def cuda_device_jit() -> Callable[[Any], Any]:
    """The CUDA decorator for device functions (imported lazily: numba.cuda is optional)."""
    from numba import cuda

    return cuda.jit(device=True)


def is_device(array: Any) -> bool:
    """True for a numba device array (real or simulated), False for NumPy arrays and None."""
    return hasattr(array, "copy_to_host") and not isinstance(array, np.ndarray)


class TrafficCounter:
    """The cuda target's launches, blocking downloads and downloaded bytes since the process
    started: each kernel launch (targets.cuda.kernel) and each download (to_host) adds to it.
    A download waits for every kernel launched before it, so `host_waits` counts the points
    where the host stops and the GPU runs dry. `graph_replays` counts the graph launches that
    replayed recorded launches (targets.cuda_graphs), each of them counted in `launches` too."""

    def __init__(self) -> None:
        self.launches = 0
        self.host_waits = 0
        self.bytes_to_host = 0
        self.graph_replays = 0


TRAFFIC = TrafficCounter()


def to_host(array: Any) -> Any:
    """`array` on the host: a device array copied down, a NumPy array (or None) as it is. The one
    place where a stage downloads what a cuda kernel left on the device (counted in TRAFFIC)."""
    if not is_device(array):
        return array
    cuda_graphs.flush()  # the launches recorded so far write what is read here
    host = array.copy_to_host()
    TRAFFIC.host_waits += 1
    TRAFFIC.bytes_to_host += host.nbytes
    return host


def pinhole(camera: Any) -> tuple[float, float, float, float]:
    """(fx, fy, cx, cy) as floats: the intrinsics a kernel takes as one argument."""
    return float(camera.fx), float(camera.fy), float(camera.cx), float(camera.cy)
