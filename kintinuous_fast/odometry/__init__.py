"""Fast dense tracking kernels (ICP, RGB-D, ICP+RGB-D) for the cpu and cuda backends.

The NumPy specification these kernels match is ``kintinuous_ref.odometry``; the modules here
have its public names and signatures:

- ``kintinuous_fast.odometry.cpu``:  numba prange loops with fixed-chunk float64 partial sums
  (deterministic on any thread count; lists in the reference's order),
- ``kintinuous_fast.odometry.cuda``: CUDA kernels following the paper's GPU design (section IV-A):
  the interest-point list built per block in shared memory with one atomic per block
  (Algorithm 1), the correspondence list and the intensity-difference sum with atomics
  (Algorithm 2), J^T J / J^T r (21 + 6 numbers, plus cost and count) reduced by a shared-memory
  tree per block, the block partials summed on the host in float64 and the 6x6 system solved
  there by Cholesky. Lists come out in atomic order (compare them as sets).

The per-correspondence maths lives once in ``kintinuous_fast.odometry.ops``. The trackers are the
reference's (same coarse-to-fine Gauss-Newton, failure checks, recovery and FOVIS switching, FOVIS
itself on the CPU as in the paper) with the fast systems underneath:

    tracker = make_tracker("icp+rgbd", config, camera, backend="auto")
    result = tracker.track(previous_frame, current_frame, model_prediction, previous_pose)

``fast_odometry(config)`` (kintinuous_ref.config's, re-exported) is the original code's "fast
odometry" option: the dense estimators skip the finest pyramid level (docs/benchmarks.md and
docs/benchmarks_archive.md measure what that costs in accuracy).
"""

from __future__ import annotations

import importlib
from types import ModuleType

from kintinuous_ref.camera import Intrinsics
from kintinuous_ref.config import Config, fast_odometry
from kintinuous_ref.errors import ConfigError
from kintinuous_ref.odometry import DENSE_METHODS, METHODS, Tracker, TrackingResult

__all__ = [
    "DENSE_METHODS",
    "METHODS",
    "Tracker",
    "TrackingResult",
    "fast_odometry",
    "kernels",
    "make_tracker",
]


def kernels(backend: str = "auto") -> ModuleType:
    """The odometry module of a backend: kintinuous_ref.odometry's functions for "ref", this
    package's cpu or cuda module otherwise ("auto": cuda where a GPU works, else cpu)."""
    from kintinuous_fast import resolve_backend_name

    name = resolve_backend_name(backend)
    if name == "ref":
        return importlib.import_module("kintinuous_ref.odometry")
    return importlib.import_module(f"kintinuous_fast.odometry.{name}")


def make_tracker(method: str, config: Config, camera: Intrinsics, backend: str = "auto") -> Tracker:
    """kintinuous_ref.odometry.make_tracker with the dense systems computed by `backend`
    ("ref", "cpu", "cuda" or "auto"); same methods, same TrackingResult."""
    from kintinuous_ref.odometry import make_tracker as ref_make_tracker

    if method not in METHODS:
        raise ConfigError(f"unknown odometry method {method!r}; choose from {', '.join(METHODS)}")
    module = kernels(backend)
    if module.__name__ == "kintinuous_ref.odometry":
        return ref_make_tracker(method, config, camera)
    return module.make_tracker(method, config, camera)
