"""The cpu backend keeps a frame's freed arrays for the next frame (targets/host_memory.py)."""

import json
import platform
import subprocess
import sys

import pytest

# A child whose malloc maps every block above 128 KiB (the environment forces it, as glibc's own
# threshold does for blocks larger than any freed so far) and whose NumPy asks for no huge pages
# (with them the count depends on where the block lands): the page faults of writing a 6.5 MB
# array (a 640x480 level's valid points) and freeing it, five times, before hold_freed_memory
# and after it (once the first array after it has grown the heap).
CHILD = """
import json, resource, sys
import numpy as np
from kintinuous_fast.targets.host_memory import hold_freed_memory

def faults_per_array():
    before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    for _ in range(5):
        points = np.empty(6 * 270_000, dtype=np.float32)
        points[::1024] = 1.0  # a value on every page
        del points
    return (resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before) / 5

unheld = faults_per_array()
held = hold_freed_memory()
faults_per_array()
json.dump({"unheld": unheld, "held": held, "after": faults_per_array()}, sys.stdout)
"""


@pytest.mark.skipif(platform.libc_ver()[0] != "glibc", reason="glibc's malloc thresholds")
def test_freed_arrays_serve_the_next_frame_without_page_faults():
    child = subprocess.run(
        [sys.executable, "-c", CHILD],
        env={"MALLOC_MMAP_THRESHOLD_": "131072", "NUMPY_MADVISE_HUGEPAGE": "0", "PATH": ""},
        capture_output=True,
        text=True,
        check=True,
    )
    counts = json.loads(child.stdout)
    assert counts["held"]
    # 1582 pages, a fault per page or per few (the kernel maps some neighbours at once)
    assert counts["unheld"] > 300
    assert counts["after"] < 5  # the heap's pages, reused


def test_the_cpu_backend_holds_freed_memory(monkeypatch):
    from kintinuous_fast import backend
    from kintinuous_fast.targets import host_memory

    calls = []
    monkeypatch.setattr(host_memory, "hold_freed_memory", lambda: calls.append(1) or True)
    backend.cpu_backend()
    assert calls == [1]


@pytest.mark.parametrize("backend_name", ["ref", "cpu"])
@pytest.mark.parametrize("odometry", ["icp", "rgbd", "icp+rgbd", "fovis/icp+rgbd"])
def test_a_run_leaves_nothing_for_the_cyclic_collector(backend_name, odometry):
    """A frame's objects are freed as soon as the next frame no longer needs them: none of the
    package's objects is in a reference cycle, which only Python's cyclic collector frees, when
    it runs. (A cycle between the ICP problem and its levels kept each frame's problems and
    arrays, about 40 MB at 640x480, until then: the process grew by hundreds of megabytes and
    each frame's arrays landed on fresh pages.)"""
    import gc

    from kintinuous_ref.backend import load_backend
    from kintinuous_ref.config import Config
    from kintinuous_ref.pipeline import run
    from kintinuous_ref.program.warmup import small_config, warmup_frames

    frames, camera, trajectory = warmup_frames()
    backend = load_backend(backend_name)
    config = small_config(Config())
    run(frames, camera, config, odometry, trajectory, backend)  # compiled, caches filled
    gc.collect()
    gc.set_debug(gc.DEBUG_SAVEALL)  # what a collection finds unreachable stays in gc.garbage
    try:
        result = run(frames, camera, config, odometry, trajectory, backend)
        gc.collect()
        cyclic = [type(item) for item in gc.garbage]
    finally:
        gc.set_debug(0)
        gc.garbage.clear()
    assert result.frames == len(frames) and result.error is None
    ours = sorted({kind.__qualname__ for kind in cyclic if kind.__module__.startswith("kintin")})
    assert ours == [], f"in reference cycles after a {backend_name} {odometry} run: {ours}"
