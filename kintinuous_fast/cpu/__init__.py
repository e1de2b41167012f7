"""The CPU backend: kintinuous_ref's public functions as parallel numba loops (prange over rows)
around the scalar functions of kintinuous_fast.ops. Used automatically where no GPU is present."""

from typing import Any

import numba


def run_parallel_above(minimum: int, loop: Any, count: int, *args: Any) -> None:
    """Call a prange `loop` with all threads for `count` >= `minimum` items, else on the calling
    thread alone: waking the other threads costs more than a small loop, and on a busy machine a
    parallel region waits for its slowest (descheduled) thread."""
    if count >= minimum:
        loop(*args)
        return
    threads = numba.get_num_threads()
    numba.set_num_threads(1)
    try:
        loop(*args)
    finally:
        numba.set_num_threads(threads)
