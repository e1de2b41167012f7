"""The raycast's per-ray functions compiled for the CPU, once: the loops of raycast.cpu and
raycast.cpu_near_starts share these dispatchers, so that each function numba compiles as a call
(`jit_called`) is compiled once.
"""

from __future__ import annotations

from kintinuous_fast.raycast import ops as raycast_ops
from kintinuous_fast.targets import cpu_jit_numpy_errors, cpu_jit_numpy_errors_called
from kintinuous_fast.tsdf import voxel

VOXELS = voxel.build_ops(cpu_jit_numpy_errors, cpu_jit_numpy_errors_called, dequantise_table=True)
OPS = raycast_ops.build_ops(cpu_jit_numpy_errors, cpu_jit_numpy_errors_called, VOXELS)
