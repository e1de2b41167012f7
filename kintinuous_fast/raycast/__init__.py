"""Model prediction (kintinuous_ref.raycast) for the cpu and cuda backends.

    ray.py            one ray's geometry and the arithmetic of its jumps, both targets
    ops.py            the march of one ray (start, step, crossing), both targets
    shading.py        one pixel: its ray marched, its vertex, normal and colour written
    cpu.py            the loop over pixel rows, two rays at a time; cpu_ops.py: the ops it
                      compiles; cpu_skip_maps.py: its empty-space maps; cpu_near_starts.py:
                      where each ray starts
    cuda.py           one thread per pixel, the brick map computed on the device

Each module's docstring says what it holds and why.
"""
