"""kintinuous_fast: the functions of kintinuous_ref with the same names and signatures, compiled
with numba (CUDA kernels, or parallel CPU loops where no GPU is present)."""
