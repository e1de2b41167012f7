# ruff: noqa: ANN001, ANN201  (numba device functions: argument types come from the call)
"""The normal equations summed on CUDA, and what both estimators' kernels share there.

Every thread sums its rows (a grid-stride loop) into a local vector of NV numbers (sums/ops.py's
add_row), the block reduces the vectors by a tree in shared memory (`block_reduce`), one partial
per block goes to global memory, and the host adds the partials in float64 (sums.sum_partials)
and solves the 6x6 system, as in the paper (section IV-A.3).

Also here: the per-element ops both estimators call (odometry/ops.py's geometry, add_row),
compiled once for CUDA, and the host helpers of every odometry kernel launch (device arrays
staged once, scratch arrays reused between Gauss-Newton iterations).
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numba import cuda

from kintinuous_fast.odometry import ops as geometry_ops
from kintinuous_fast.targets import cuda_device_jit, cuda_graphs
from kintinuous_fast.targets.cuda import BLOCK_1D, grid_1d, to_device

from . import NV
from .ops import build_ops

__all__ = [
    "BLOCK",
    "DEVICE",
    "GEOMETRY",
    "MAX_BLOCKS",
    "add_column",
    "add_row",
    "block_reduce",
    "counter",
    "f64",
    "gated",
    "open_gate",
    "reduction_blocks",
    "rounded_up",
    "scratch",
    "stage",
    "upload",
    "zero",
]

# Blocks of the reduction kernels at most (each thread then loops over several rows): enough to
# fill a GPU, few enough that the host adds the partials in microseconds.
MAX_BLOCKS = 1024
BLOCK = BLOCK_1D  # threads per block of every odometry kernel (a power of two: the tree halves it)

# The decorator of every per-element op on CUDA; the ops both estimators call, compiled once.
DEVICE = cuda_device_jit()
GEOMETRY = geometry_ops.build_ops(DEVICE)
# Module-level names: numba resolves the device functions as globals of the kernels.
_ops = build_ops(DEVICE)
zero = _ops.zero
add_row = _ops.add_row
add_column = _ops.add_column


@cuda.jit(device=True)
def block_reduce(acc, shared, partials):
    """Tree reduction of every thread's NV sums in shared memory; thread 0 writes the block's.
    The block index is read before the first barrier: numba's simulator swaps this module's
    `cuda` for its kernel context while a thread is inside, and the thread that swapped it may
    leave first and swap it back (the kernels that call this live in other modules)."""
    t = cuda.threadIdx.x
    block = cuda.blockIdx.x
    for s in range(NV):
        shared[s, t] = acc[s]
    cuda.syncthreads()
    half = BLOCK // 2
    while half > 0:
        if t < half:
            for s in range(NV):
                shared[s, t] += shared[s, t + half]
        cuda.syncthreads()
        half //= 2
    if t == 0:
        for s in range(NV):
            partials[block, s] = shared[s, 0]


# The gate of every Gauss-Newton kernel: the first slots of the state vector the device loop
# keeps (odometry/frame_on_device.py). Slot GATE_FAILED is non-zero once a step of the frame has
# failed; slot GATE_DONE_LEVEL is the pyramid level whose steps have converged. A gated kernel
# returns at once, so a frame launches the same kernels whatever its data do.
GATE_FAILED = 0
GATE_DONE_LEVEL = 1
ANY_LEVEL = -1  # the `level` of a launch that no level's convergence skips (a single system)


@cuda.jit(device=True)
def gated(gate, level):
    """True when a kernel of `level` has nothing to do: the frame failed or the level is done."""
    return gate[GATE_FAILED] != 0.0 or (level >= 0 and gate[GATE_DONE_LEVEL] == level)


_OPEN_GATE: list[Any] = []


def open_gate() -> Any:
    """A gate that never closes, for kernels launched one system at a time by the host."""
    if not _OPEN_GATE:
        _OPEN_GATE.append(cuda.to_device(np.array([0.0, -1.0])))
    return _OPEN_GATE[0]


def reduction_blocks(count: int) -> int:
    """Blocks of a reduction kernel over `count` rows (at most MAX_BLOCKS)."""
    return min(grid_1d(count, BLOCK), MAX_BLOCKS)


def stage(array: Any) -> Any:
    """A device array (uploaded once if a NumPy array is given; None stays None)."""
    return None if array is None else to_device(array)


def f64(array: Any) -> Any:
    """A float64 device array (host arrays converted and uploaded)."""
    return to_device(array, np.float64)


# Device arrays reused from one Gauss-Newton iteration to the next: creating one costs numba
# more host time (an allocation through the driver, a Python object, its finalizer) than the
# kernels it feeds take on the GPU. Only for arrays a call writes and reads back itself: the
# copies and kernels of the one stream run in order, so a later call's writes wait for them.
_SCRATCH: dict[tuple, Any] = {}


def scratch(name: str, shape: tuple[int, ...], dtype: Any = np.float64) -> Any:
    """The scratch device array `name` of this shape and type (made on first use)."""
    key = (name, shape, np.dtype(dtype))
    if key not in _SCRATCH:
        _SCRATCH[key] = cuda.device_array(shape, dtype=dtype)
    return _SCRATCH[key]


def upload(name: str, array: np.ndarray) -> Any:
    """`array` copied into the scratch device array `name` of its shape and type."""
    device = scratch(name, array.shape, array.dtype)
    cuda_graphs.flush()  # launches recorded before the copy run before it
    device.copy_to_device(np.ascontiguousarray(array))
    return device


def rounded_up(count: int) -> int:
    """The power of two at or above `count` (>= 1): few shapes, so few scratch arrays."""
    return 1 << max(count - 1, 0).bit_length()


def counter(dtype: Any = np.int32) -> Any:
    """A device array of one zero, for a kernel's atomic count."""
    return cuda.to_device(np.zeros(1, dtype=dtype))
