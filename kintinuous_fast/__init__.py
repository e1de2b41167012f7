"""kintinuous_fast: the functions of kintinuous_ref with the same names and signatures, compiled
with numba: CUDA kernels where a GPU is present, CPU loops run on several threads where not.

The package mirrors kintinuous_ref stage by stage (docs/architecture.md). Each stage is a
package whose `ops.py` holds its per-element maths written once (filter one pixel, update one
voxel, march one ray, one pair's rows of the normal equations), compiled for both targets;
`cpu.py` holds the loops around it (targets/cpu.py runs them on all threads), `cuda.py` the
kernels; each has its reference module's public names and signatures
(tests/test_stage_contract.py).

    preprocess/   ops.py, cpu.py, cuda.py, host.py (weight tables, checks, the stage order)
    tsdf/         ops.py (integrate one voxel), voxel.py (the stored voxel), volume.py
                  (FastTsdfVolume), cpu.py, cuda.py
    raycast/      ray.py, ops.py (one ray), shading.py (one pixel), cpu.py, cuda.py
    colour/       cpu.py, cuda.py (the per-pixel weight lives in tsdf/ops.py)
    odometry/     one estimator per package as in kintinuous_ref.odometry: icp/, rgbd/,
                  combined.py, solve/, sums/ (the normal equations' sums); cpu.py and cuda.py
                  are the stage modules (that target's systems and make_tracker)
    targets/      the decorators of each target and their helpers (threads, device arrays,
                  the compile cache)
    backend.py    the backends the pipeline uses (kintinuous_ref.backend.Backend)

A backend is found by the reference's `load_backend(name)` ("cpu", "cuda", "ref" or "auto"),
which looks the fast backends up through the `kintinuous.backends` entry points; this package
exports that same function:

    backend = load_backend("auto")
    frame = backend.preprocess.preprocess_frame(colour, depth, camera, config.preprocess)
    tracker = backend.odometry.make_tracker("icp+rgbd", config, camera)

With cuda, arrays stay where they are given: device arrays in, device arrays out, so a pipeline
keeps its frames, maps and volume in GPU memory (`backend.upload`, `backend.predict_surface`).
"""

from __future__ import annotations

from kintinuous_fast.backend import cuda_is_simulated, cuda_status
from kintinuous_ref.backend import backend_status, load_backend

__all__ = ["backend_status", "cuda_is_simulated", "cuda_status", "load_backend"]
