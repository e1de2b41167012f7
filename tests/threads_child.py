"""Python code run in a child process with a numba thread count of its own: numba reads
NUMBA_NUM_THREADS once, when it starts, so a test that needs a team of some size starts one."""

import json
import os
import subprocess
import sys
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
