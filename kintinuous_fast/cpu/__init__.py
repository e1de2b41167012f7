"""The CPU backend: kintinuous_ref's public functions as parallel numba loops (prange over rows)
around the scalar functions of kintinuous_fast.ops. Used automatically where no GPU is present."""
