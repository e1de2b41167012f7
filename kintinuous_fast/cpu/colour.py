"""The colour stage of the CPU backend: kintinuous_ref.colour's colour_weights itself.

It is three whole-image NumPy operations (depth > 0, times the discontinuity mask, times |n_z|),
about 1 ms at 640x480 and bandwidth-bound: a numba loop would save a fraction of that and add a
second implementation to keep equal to the specification, so the reference's function is the
cpu backend's (the cuda backend needs its own kernel only because its frames are on the GPU).
"""

from kintinuous_ref.colour import colour_weights

__all__ = ["colour_weights"]
