"""Fast dense tracking kernels (ICP, RGB-D, ICP+RGB-D) for the cpu and cuda backends.

Owner: engineer K2. The NumPy specification these kernels match is ``kintinuous_ref.odometry``.
"""
