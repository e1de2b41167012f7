"""Fast dense tracking kernels (ICP, RGB-D, ICP+RGB-D) for the cpu and cuda backends.

The NumPy specification these kernels match is ``kintinuous_ref.odometry``; the modules here
have its public names and signatures:

- ``kintinuous_fast.odometry.cpu``:  numba loops, on all threads, with fixed-chunk float64 sums
  (deterministic on any thread count; lists in the reference's order),
- ``kintinuous_fast.odometry.cuda``: CUDA kernels following the paper's GPU design (section IV-A):
  the interest-point list built per block in shared memory with one atomic per block
  (Algorithm 1), the correspondence list and the intensity-difference sum with atomics
  (Algorithm 2), J^T J / J^T r (21 + 6 numbers, plus cost and count) reduced by a shared-memory
  tree per block, the block partials summed on the host in float64 and the 6x6 system solved
  there by Cholesky. Lists come out in atomic order (compare them as sets).

The per-correspondence maths lives once in ``kintinuous_fast.odometry.ops``. The trackers are the
reference's (same coarse-to-fine Gauss-Newton, failure checks, recovery and FOVIS switching, FOVIS
itself on the CPU as in the paper, in ``host.py``) with the fast systems underneath:

    tracker = select_backend("cpu").odometry.make_tracker("icp+rgbd", config, camera)
    result = tracker.track(previous_frame, current_frame, model_prediction, previous_pose)
"""
