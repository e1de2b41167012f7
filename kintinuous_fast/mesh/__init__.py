"""Marching cubes (kintinuous_ref.marching_cubes) for the cpu and cuda backends.

ops.py     one cube's case and edge crossings, one row's counts, vertices and triangles,
           both targets
cpu.py     the three passes as loops over rows on all threads
cuda.py    the three passes as kernels, one thread per row, and a prefix sum on the device
"""
