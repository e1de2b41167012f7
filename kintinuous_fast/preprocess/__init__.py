"""Frame preprocessing (kintinuous_ref.preprocess) for the cpu and cuda backends.

    ops.py            one pixel's maths (filters, pyramids, vertices, normals, gradients), both
                      targets
    cpu.py            row loops around it; cpu_bilateral.py: the cpu bilateral filter
    cuda.py           one kernel per stage, a thread per pixel
    host.py           weight tables, input checks and the stage order, shared by both

Each module's docstring says what it holds and why.
"""
