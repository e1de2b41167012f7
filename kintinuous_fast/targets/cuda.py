"""The CUDA backend: kintinuous_ref's public functions as numba.cuda kernels around the scalar
functions of each stage's ops.py.

Arrays stay where they are given: a function called with device arrays returns device arrays
(so a pipeline keeps pyramids, maps and volumes in GPU memory for the whole run), one called with
NumPy arrays uploads them, computes on the GPU and returns NumPy arrays (what the equivalence
tests use). Runs on numba's CUDA simulator too (NUMBA_ENABLE_CUDASIM=1), very slowly.
"""

from __future__ import annotations

import sys
import warnings
from typing import Any

import numpy as np
from numba import config as numba_config
from numba import cuda

from kintinuous_fast.targets import TRAFFIC, cuda_graphs, is_device, to_host

# Threads per block of the per-pixel kernels: 16 x 16, x along image rows (coalesced reads).
BLOCK_2D = (16, 16)
# Threads per block of 1-D kernels (voxel columns, lists).
BLOCK_1D = 128

# numba warns of every launch of fewer than 128 blocks, once per grid size. The coarse pyramid
# levels, the interest-point and pair lists and the reductions launch such grids by design
# (their work is small, not spread thin), so a run would print hundreds of these lines into its
# progress bar. (numba may wrap its messages in a terminal's bold: \x1b[1m ... \x1b[0m.)
SMALL_GRID_WARNING = r"(?:\x1b\[[0-9;]*m)?Grid size \d+ will likely result in GPU under-utilization"


def quiet_small_grids() -> None:
    """Silence numba's low-occupancy warning (SMALL_GRID_WARNING), and only that one."""
    warnings.filterwarnings("ignore", message=SMALL_GRID_WARNING)


quiet_small_grids()


class CountedKernel:
    """A numba.cuda kernel whose launches are counted in targets.TRAFFIC (and recorded for a
    graph inside a segment, targets.cuda_graphs): `kernel[grid, block]` and every attribute are
    the kernel's own; only the launch goes through here."""

    def __init__(self, dispatcher: Any) -> None:
        self.dispatcher = dispatcher

    def __getitem__(self, configuration: Any) -> Any:
        def counted_launch(*arguments: Any) -> None:
            TRAFFIC.launches += 1
            if cuda_graphs.recording():
                cuda_graphs.record(self.dispatcher, configuration, arguments)
            else:
                self.dispatcher[configuration](*arguments)

        return counted_launch

    def __getattr__(self, name: str) -> Any:
        return getattr(self.dispatcher, name)


def kernel(function: Any) -> CountedKernel:
    """`cuda.jit` for a kernel (not a device function), its launches counted: the decorator of
    every kernel of the cuda backend."""
    return CountedKernel(cuda.jit(function))


def to_device(array: Any, dtype: Any = None) -> Any:
    """A device array holding `array` (no copy if it already is one of the right dtype)."""
    if is_device(array):
        if dtype is not None and array.dtype != np.dtype(dtype):
            raise TypeError(f"device array is {array.dtype}, expected {np.dtype(dtype)}")
        return array
    host = np.ascontiguousarray(array, dtype=dtype)
    return cuda.to_device(host)


# Device buffers kept for reuse, per role, shape and type: a stage that takes its outputs from
# here gets the same addresses frame after frame, so its launches repeat exactly and can be
# replayed as a graph (targets.cuda_graphs), and the host makes no allocation per frame.
_POOL: dict[tuple, list[Any]] = {}
_POOL_BASELINES: dict[tuple, list[tuple[int, int]]] = {}


def pooled_array(role: str, shape: tuple[int, ...], dtype: Any) -> Any:
    """A device array for `role` of this shape and type, its contents undefined: one made
    before and no longer referred to (by a frame, a view of it or a recorded launch), else a
    new one. Safe to reuse: every kernel and copy runs in the one stream order, so writes to a
    reused buffer wait for the reads queued before them."""
    key = (role, tuple(int(n) for n in shape), np.dtype(dtype).str)
    arrays = _POOL.setdefault(key, [])
    baselines = _POOL_BASELINES.setdefault(key, [])
    for index in range(len(arrays)):
        if _references(arrays, index) == baselines[index]:
            return arrays[index]
    arrays.append(cuda.device_array(key[1], dtype=key[2]))
    baselines.append(_references(arrays, len(arrays) - 1))
    return arrays[-1]


def pooled_arrays(role: str, specs: tuple[tuple[tuple[int, ...], str], ...]) -> tuple[Any, ...]:
    """Device arrays for `role`, one per (shape, dtype string) of `specs`, taken and given back
    together: a group made before none of whose arrays is referred to any more, else a new one.
    For a stage that writes many arrays of one size (a frame's pyramid): pooled_array would
    scan its size's whole list for each of them, here one scan finds a free group."""
    key = ("group", role, specs)
    groups = _POOL.setdefault(key, [])
    baselines = _POOL_BASELINES.setdefault(key, [])
    for group, baseline in zip(groups, baselines, strict=True):
        if all(_references(group, index) == baseline[index] for index in range(len(group))):
            return group
    groups.append(tuple(cuda.device_array(shape, dtype=dtype) for shape, dtype in specs))
    baselines.append([_references(groups[-1], index) for index in range(len(specs))])
    return groups[-1]


def _references(arrays: list[Any] | tuple, index: int) -> tuple[int, int, int]:
    """How many references the array and its memory have: measured once when only the pool
    holds it (the baseline), then compared. A view refers to the memory, not to the array: in
    the simulator by a Python reference to its NumPy buffer, on a GPU by a weak proxy that
    counts itself in the memory's `refct` instead."""
    memory = _memory(arrays[index])
    views = 0 if numba_config.ENABLE_CUDASIM else memory.refct
    return sys.getrefcount(arrays[index]), sys.getrefcount(memory), views


def _memory(array: Any) -> Any:
    """The object a device array's views keep alive: numba's memory pointer, or the NumPy
    buffer of a simulated array."""
    return array._ary if numba_config.ENABLE_CUDASIM else array.gpu_data


# Page-locked host buffers, one per device buffer that takes uploads (keyed by its address,
# shape and type), kept for the process: the copy engine reads pinned memory directly and
# without a host wait, where a copy from pageable memory first goes through a staging copy of
# the driver's and returns only when it is done.
_STAGING: dict[tuple, cuda_graphs.Staging] = {}


def copy_up(device: Any, host: np.ndarray) -> Any:
    """`device` (returned) filled with `host` in stream order: after every launch queued or
    recorded before, and before every one after, with no host wait (cuda_graphs.upload). The
    values go through `device`'s own pinned buffer, which the host fills only once the copy
    before has read it."""
    staging = _staging_for(device)
    if staging.queued:  # a recorded copy has yet to read the buffer's present contents
        cuda_graphs.flush()
    staging.copied.synchronize()  # the copy before has read it (long since, in a pipeline)
    staging.host[...] = host
    cuda_graphs.upload(device, staging)
    return device


def _staging_for(device: Any) -> cuda_graphs.Staging:
    key = (cuda_graphs.device_address(device), device.shape, device.dtype.str)
    if key not in _STAGING:
        host = cuda.pinned_array(device.shape, dtype=device.dtype)
        _STAGING[key] = cuda_graphs.Staging(host=host, copied=cuda.event())
    return _STAGING[key]


@cuda_graphs.segment
def upload_image(image: np.ndarray) -> Any:
    """A raw frame image on the device, in a pooled buffer (frames alternate between two),
    copied up through that buffer's pinned host buffer without a host wait (copy_up). A segment
    of its own: with graphs on, the copy replays as a one-node graph, which skips the Python
    that numba's copy_to_device runs around the driver call (about 0.6 ms an image, profiled on
    the H100's host, docs/benchmarks.md)."""
    if is_device(image):
        return image
    return copy_up(pooled_array("raw image", image.shape, image.dtype), image)


def like_input(result: Any, given: Any) -> Any:
    """`result` (a device array) back on the host when the caller gave a host array."""
    return result if is_device(given) else to_host(result)


def grid_2d(height: int, width: int, block: tuple[int, int] = BLOCK_2D) -> tuple[int, int]:
    """Blocks covering a height x width image with threads (x = column, y = row)."""
    return (width + block[0] - 1) // block[0], (height + block[1] - 1) // block[1]


def grid_1d(count: int, block: int = BLOCK_1D) -> int:
    return max(1, (count + block - 1) // block)
