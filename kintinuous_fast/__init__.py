"""kintinuous_fast: the functions of kintinuous_ref with the same names and signatures, compiled
with numba: CUDA kernels where a GPU is present, CPU loops run on several threads where not.

The package mirrors kintinuous_ref stage by stage. Each stage is a package with the same
three files: `ops.py`, its per-element maths written once (filter one pixel, update one voxel,
march one ray, one pair's rows of the normal equations) and compiled for both targets; `cpu.py`,
the loops around it (targets/cpu.py runs them on all threads); `cuda.py`, the kernels around it.

    preprocess/   ops.py cpu.py cuda.py, host.py (weight tables, checks, the stage order)
    tsdf/         ops.py (integrate one voxel), voxel.py (the stored voxel), volume.py
                  (FastTsdfVolume), cpu.py, cuda.py
    raycast/      ops.py (one ray), cpu.py, cuda.py
    colour/       cpu.py, cuda.py (the per-pixel weight lives in tsdf/ops.py)
    odometry/     ops.py (one pair's rows), cpu.py, cuda.py, host.py (the trackers over either)
    targets/      the decorators of each target and their helpers (threads, device arrays)
    backend.py    the backends the pipeline uses (kintinuous_ref.backend.Backend)

One entry point: `select_backend(name)` ("cpu", "cuda", "ref" or "auto"), the same object that
kintinuous_ref.backend.load_backend finds through the `kintinuous.backends` entry points:

    backend = select_backend("auto")
    frame = backend.preprocess.preprocess_frame(colour, depth, camera, config.preprocess)
    tracker = backend.odometry.make_tracker("icp+rgbd", config, camera)

With cuda, arrays stay where they are given: device arrays in, device arrays out, so a pipeline
keeps its frames, maps and volume in GPU memory (`backend.upload`, `backend.predict_surface`).
"""

from __future__ import annotations

from kintinuous_fast.backend import cuda_is_simulated, cuda_status
from kintinuous_ref.backend import Backend, backend_status, load_backend

__all__ = ["backend_status", "cuda_is_simulated", "cuda_status", "select_backend"]


def select_backend(name: str = "auto") -> Backend:
    """The backend called `name` (ref, cpu, cuda or auto); ConfigError if it cannot run here."""
    return load_backend(name)
