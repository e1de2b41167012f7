"""Python code run in a child process with a numba thread count of its own: numba reads
NUMBA_NUM_THREADS once, when it starts, so a test that needs a team of some size starts one."""

import json
import os
import subprocess
import sys
from collections.abc import Callable
from typing import Any

TESTS = os.path.dirname(os.path.abspath(__file__))


def run_with_threads(code: str, threads: int, timeout: float = 1200) -> Any:
    """The JSON that `code` prints last, run with NUMBA_NUM_THREADS=`threads` and this folder
    importable; a failing child fails the caller with the end of its stderr."""
    paths = [TESTS, *filter(None, [os.environ.get("PYTHONPATH")])]
    environment = {
        **os.environ,
        "NUMBA_NUM_THREADS": str(threads),
        "PYTHONPATH": os.pathsep.join(paths),
    }
    child = subprocess.run(
        [sys.executable, "-c", code],
        env=environment,
        capture_output=True,
        text=True,
        timeout=timeout,
        check=False,
    )
    assert child.returncode == 0, child.stderr[-3000:]
    return json.loads(child.stdout.strip().splitlines()[-1])


def on_both_paths(run: Callable[[int], Any]) -> dict[str, Any]:
    """run(threads) for 1, 2 and 7 threads on each of run_parallel's paths (numba's threads
    where its threading layer spins, the helper team), then on 7 with every loop shared (no
    work threshold) on each: {"<path>, <threads> threads[, every loop shared]": result}. For a
    child process: the thresholds stay changed."""
    from kintinuous_fast.targets import cpu

    paths = {"numba's threads": cpu.native_threads(), "the helper team": False}
    runs = {}
    for shared in (False, True):
        if shared:
            cpu.MIN_SECONDS_PER_THREAD = cpu.MIN_SECONDS_PER_HELPER = 1e-12
        for path, native in paths.items():
            cpu.native_threads = lambda native=native: native
            for threads in (7,) if shared else (1, 2, 7):
                runs[f"{path}, {threads} threads" + ", every loop shared" * shared] = run(threads)
    return runs
