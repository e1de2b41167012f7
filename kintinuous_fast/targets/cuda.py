"""The CUDA backend: kintinuous_ref's public functions as numba.cuda kernels around the scalar
functions of each stage's ops.py.

Arrays stay where they are given: a function called with device arrays returns device arrays
(so a pipeline keeps pyramids, maps and volumes in GPU memory for the whole run), one called with
NumPy arrays uploads them, computes on the GPU and returns NumPy arrays (what the equivalence
tests use). Runs on numba's CUDA simulator too (NUMBA_ENABLE_CUDASIM=1), very slowly.
"""

from __future__ import annotations

import warnings
from typing import Any

import numpy as np
from numba import cuda

from kintinuous_fast.targets import TRAFFIC, is_device, to_host

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
    """A numba.cuda kernel whose launches are counted in targets.TRAFFIC: `kernel[grid, block]`
    and every attribute are the kernel's own; only the launch goes through here."""

    def __init__(self, dispatcher: Any) -> None:
        self.dispatcher = dispatcher

    def __getitem__(self, configuration: Any) -> Any:
        launch = self.dispatcher[configuration]

        def counted_launch(*arguments: Any) -> None:
            TRAFFIC.launches += 1
            launch(*arguments)

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


# Page-locked host buffers for the frames' raw images, one per shape and dtype (a frame's depth
# and colour), kept for the process: the copy engine reads pinned memory directly, where a copy
# from pageable memory first goes through a staging copy of the driver's.
_STAGING: dict[tuple[tuple[int, ...], str], np.ndarray] = {}


def upload_image(image: np.ndarray) -> Any:
    """A raw frame image on the device, copied up through this shape's pinned buffer. The copy
    is synchronous, so the buffer is free for the next frame when this returns."""
    if is_device(image):
        return image
    key = (image.shape, image.dtype.str)
    if key not in _STAGING:
        _STAGING[key] = cuda.pinned_array(image.shape, dtype=image.dtype)
    staging = _STAGING[key]
    staging[...] = image
    return cuda.to_device(staging)


def like_input(result: Any, given: Any) -> Any:
    """`result` (a device array) back on the host when the caller gave a host array."""
    return result if is_device(given) else to_host(result)


def grid_2d(height: int, width: int, block: tuple[int, int] = BLOCK_2D) -> tuple[int, int]:
    """Blocks covering a height x width image with threads (x = column, y = row)."""
    return (width + block[0] - 1) // block[0], (height + block[1] - 1) // block[1]


def grid_1d(count: int, block: int = BLOCK_1D) -> int:
    return max(1, (count + block - 1) // block)
