"""`kintinuous warmup`: compile a backend's kernels before a run needs them, and say how long
each one took.

numba compiles a kernel the first time it is called with new argument types and keeps the
machine code in its on-disk cache, so only the first run after an installation pays for it.
Types, not sizes, decide what is compiled, so a few tiny synthetic frames (160x120, a 64^3
volume) through the real pipeline compile everything a full-size run of the same configuration
and odometry will call. Timing each stage of those frames says how long each stage took to
compile; numba's "numba:compile" events (fired only when a kernel is really compiled, not when
it is loaded from the cache) say which kernels the time went into.

`reconstruct` warms up before its progress bar starts, so the bar's rate and time left count
frames only, and it says how long the wait was.

Compilation is single-threaded, so on a machine with two or more cores the first warm-up
compiles in two child processes at once, each one half of the stages (PARTS below) with the
other half taken from the reference. Both write numba's on-disk cache, from which this process
then loads everything in about a second.
"""

from __future__ import annotations

import contextlib
import functools
import json
import multiprocessing
import os
import signal
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Iterator
from concurrent.futures import ProcessPoolExecutor
from contextlib import contextmanager
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

from kintinuous_ref.backend import Backend, ReferenceBackend, load_backend
from kintinuous_ref.config import Config
from kintinuous_ref.datasets.tum import Frame
from kintinuous_ref.errors import KintinuousError
from kintinuous_ref.odometry import DENSE_METHODS, METHODS
from kintinuous_ref.pipeline import GROUNDTRUTH, STAGES, run
from kintinuous_ref.signals import Interrupted

# What a run still has to compile, by what it calls and what numba's cache holds: the kernels of
# a run with known poses (preprocessing, integration, colour), those a tracked run adds to them
# (raycast, odometry) when the first are cached, or both.
COMPILE_MAPPING, COMPILE_TRACKING, COMPILE_ALL = "mapping", "tracking", "mapping and tracking"
COMPILE_PARTS = (COMPILE_MAPPING, COMPILE_TRACKING, COMPILE_ALL)
# Wall seconds of each part's compile on the 2-core machine, idle and under a load average of
# about 10 from other users' work (docs/reliability.md, "The first run"): what is said before a
# compile on a machine that never measured one.
KNOWN_COMPILE_SECONDS = {
    COMPILE_MAPPING: (11, 189),
    COMPILE_TRACKING: (16, 334),
    COMPILE_ALL: (25, 570),
}

FRAMES = 3  # the first fuses, the second tracks, the third tracks against a raycast model
WIDTH, HEIGHT = 160, 120
RESOLUTION = 64


@dataclass
class WarmupReport:
    backend: str
    seconds: float = 0.0
    stage_seconds: dict[str, float] = field(default_factory=dict)  # slowest frame per stage
    kernel_seconds: dict[str, float] = field(default_factory=dict)  # compiled here, outermost
    methods: list[str] = field(default_factory=list)

    def as_dict(self) -> dict[str, Any]:
        return {
            "backend": self.backend,
            "seconds": self.seconds,
            "methods": self.methods,
            "stage_seconds": self.stage_seconds,
            "kernel_seconds": self.kernel_seconds,
        }


@functools.lru_cache(maxsize=1)
def warmup_frames() -> tuple[list[Frame], Any, Any]:
    """Three small frames of the built-in desk scene, its camera and its ground truth."""
    from kintinuous_ref.datasets.synthetic import make_scenario

    scenario = make_scenario("desk", frames=FRAMES, width=WIDTH, height=HEIGHT)
    stamps = scenario.trajectory.timestamps
    frames = [Frame(i, float(stamps[i]), *scenario.render(i)) for i in range(FRAMES)]
    return frames, scenario.camera, scenario.trajectory


def small_config(config: Config) -> Config:
    """`config` with a 64^3 volume: the same kernels as the full-size run, seconds less work."""
    shift = min(config.volume.shift_threshold, RESOLUTION // 4)
    volume = replace(config.volume, resolution=RESOLUTION, shift_threshold=shift)
    return replace(config, volume=volume)


def methods_for(odometry: str) -> list[str]:
    """The odometry methods to warm up: "all" means every dense tracker and FOVIS switching over
    the joint one (the others reuse their kernels)."""
    if odometry == "all":
        return [*DENSE_METHODS, "fovis/icp+rgbd"]
    if odometry != GROUNDTRUTH and odometry not in METHODS:
        raise KintinuousError(f"unknown odometry {odometry!r}")
    return [odometry]


# The stage of a warm-up's table that holds the two compiling child processes' wall time.
COMPILING = "compiling"


def warm_up(
    backend: Backend,
    config: Config,
    odometry: str = "all",
    progress: Callable[[str], None] | None = None,
    parallel: bool = True,
) -> WarmupReport:
    """Run each method of `methods_for(odometry)` over the warm-up frames on `backend` and
    return how long each stage and each compiled kernel took. `progress(method)` is called after
    each method. With `parallel` and a cpu backend on two or more cores, two child processes
    compile first (see the module docstring); their kernels' times are in the report. At the
    end the backend records the warm-up, so that its kernels_cached says so from then on, and
    where this call compiled what the cache lacked, its wall time (compile_estimate reads it)."""
    report = WarmupReport(backend.name, methods=methods_for(odometry))
    start = time.perf_counter()
    compiled: dict[str, float] = {}
    tracking = report.methods != [GROUNDTRUTH]
    part = kernels_to_compile(backend, tracking)
    if parallel and (os.cpu_count() or 1) >= 2 and part is not None:
        compiled = compile_in_two_processes(backend.name, config, report.methods)
        # the stages below then load what the two processes compiled: most of the wait is here
        report.stage_seconds[COMPILING] = time.perf_counter() - start
    with compile_events() as kernels:
        for method in report.methods:
            result = _run_warmup(backend, config, method)
            for stage in STAGES:
                if stage != "total" and result.timings_ms[stage]:
                    slowest = max(result.timings_ms[stage]) / 1000.0
                    report.stage_seconds[stage] = report.stage_seconds.get(stage, 0.0) + slowest
            report.stage_seconds["mesh"] = report.stage_seconds.get("mesh", 0.0) + _mesh_warmup(
                backend, result
            )
            if progress is not None:
                progress(method)
    backend.record_warm_up(tracking)
    report.seconds = time.perf_counter() - start
    compiled.update(kernels)
    report.kernel_seconds = dict(sorted(compiled.items(), key=lambda item: -item[1]))
    if part is not None and report.kernel_seconds and parallel:
        backend.record_compile_seconds(part, report.seconds)  # what the next such compile takes
    return report


def kernels_to_compile(backend: Backend, tracking: bool) -> str | None:
    """Which of COMPILE_PARTS a run (with or without `tracking`) on `backend` would compile
    first; None when numba's cache holds them all (or the backend compiles nothing ahead)."""
    if backend.kernels_cached(tracking):
        return None
    if not tracking:
        return COMPILE_MAPPING
    return COMPILE_TRACKING if backend.kernels_cached(False) else COMPILE_ALL


def compile_estimate(backend: Backend, part: str) -> str:
    """How long compiling `part` will take: the last such compile measured here, else the range
    measured on the 2-core machine."""
    measured = backend.compile_seconds(part)
    if measured is not None:
        return f"about {measured:.0f} s, as measured on this machine"
    idle, busy = KNOWN_COMPILE_SECONDS[part]
    return f"{idle}-{busy} s on 2 cores, idle to a load of 10; not yet measured here"


def _mesh_warmup(backend: Backend, result: Any) -> float:
    """Seconds to mesh the warm-up's volume with the backend's marching cubes (compiling them
    the first time), so that a run's first mesh does not compile."""
    from kintinuous_ref.mesh import extract_mesh

    start = time.perf_counter()
    extract_mesh(backend.host_volume(result.volume), contour=backend.mesh.marching_cubes)
    return time.perf_counter() - start


def _run_warmup(backend: Backend, config: Config, method: str) -> Any:
    frames, camera, trajectory = warmup_frames()
    result = run(frames, camera, small_config(config), method, trajectory, backend)
    if result.interrupted:  # run() keeps a signal as its result's; the command ends on it
        raise Interrupted(result.signal_name)
    if result.error is not None:
        raise result.error
    return result


# The two halves of a cold warm-up, each compiled in its own child process: the model (the
# volume, the raycast that reads it and its mesh) and the tracking (preprocessing, and the
# odometry and colour weights that read its pyramids). Their compile times are close (about 33 s
# each on the 2-core machine), and each half takes the other's stages from the reference, whose
# outputs have the types the fast stages take in a real run (NumPy arrays, float32 maps), so
# nothing is compiled for the wrong types.
MODEL, TRACKING = "model", "tracking"
PARTS = (MODEL, TRACKING)


class _WithTracking:
    """`base` (its volume, raycast and the rest) with the preprocessing, odometry and colour
    weights of `tracking`."""

    def __init__(self, base: Backend, tracking: Backend) -> None:
        self._base = base
        self.preprocess, self.odometry = tracking.preprocess, tracking.odometry
        self.colour = tracking.colour

    def __getattr__(self, name: str) -> Any:
        return getattr(self._base, name)


def _compile_part(backend_name: str, config: Config, methods: list[str], part: str) -> dict:
    """In a child process: compile the `part` (MODEL or TRACKING) of each method's kernels."""
    backend, reference = load_backend(backend_name), ReferenceBackend()
    if part == MODEL:
        mixed = _WithTracking(backend, tracking=reference)
    else:  # on a reference volume, raycast by the reference
        mixed = _WithTracking(reference, tracking=backend)
    with compile_events() as kernels:
        for method in methods:
            result = _run_warmup(mixed, config, method)  # type: ignore[arg-type]
            if part == MODEL:  # the volume's mesh belongs with the volume
                _mesh_warmup(mixed, result)  # type: ignore[arg-type]
    return kernels


def compile_in_two_processes(backend_name: str, config: Config, methods: list[str]) -> dict:
    """Compile the model and the tracking halves in two child processes at once (spawned: a
    fresh interpreter each, nothing inherited from this one's numba state); seconds per
    kernel compiled there. A signal or an error here ends both children before it goes on:
    a compile left running would outlive the command by a minute."""
    context = multiprocessing.get_context("spawn")
    pool = ProcessPoolExecutor(max_workers=2, mp_context=context)
    try:
        parts = [pool.submit(_compile_part, backend_name, config, methods, part) for part in PARTS]
        compiled: dict[str, float] = {}
        for future in parts:
            compiled.update(future.result())
    except BaseException:
        _end_workers(pool)
        raise
    pool.shutdown()
    return compiled


def _end_workers(pool: ProcessPoolExecutor) -> None:
    """Terminate a pool's workers and wait for them (the executor's own shutdown would wait
    for their compiles to finish)."""
    workers = list((getattr(pool, "_processes", None) or {}).values())
    pool.shutdown(wait=False, cancel_futures=True)
    for worker in workers:
        worker.terminate()
    for worker in workers:
        worker.join(timeout=10)
        if worker.is_alive():
            worker.kill()
            worker.join()


@contextmanager
def compile_events() -> Iterator[dict[str, float]]:
    """Seconds per kernel that numba compiles inside the block (outermost compilations only: a
    kernel's time includes the device functions it compiles on the way). Empty without numba."""
    seconds: dict[str, float] = {}
    try:
        from numba.core import event
    except ImportError:
        yield seconds
        return

    open_events: list[tuple[str, float]] = []

    class Listener(event.Listener):
        def on_start(self, item: Any) -> None:
            dispatcher = item.data["dispatcher"]
            name = f"{dispatcher.py_func.__module__}.{dispatcher.py_func.__qualname__}"
            open_events.append((name, time.perf_counter()))

        def on_end(self, item: Any) -> None:
            name, began = open_events.pop()
            if not open_events:  # an outermost compilation
                seconds[name] = seconds.get(name, 0.0) + time.perf_counter() - began

    with event.install_listener("numba:compile", Listener()):
        yield seconds


def warm_up_from_empty_cache(
    backend: str, odometry: str, serial: bool = False, timeout: float = 1800.0
) -> dict:
    """The warm-up in a child process whose numba cache is an empty temporary folder: what a
    fresh installation pays, measured without touching this installation's cache. The child
    and its compile workers run in a process group of their own, which ends with this call
    however it ends (a signal included), before the folder is removed."""
    with tempfile.TemporaryDirectory(prefix="kintinuous-numba-cache-") as cache:
        environment = {**os.environ, "NUMBA_CACHE_DIR": cache}
        cli = [sys.executable, "-m", "kintinuous_ref.program.cli", "warmup", "--json"]
        command = [*cli, "--backend", backend, "--odometry", odometry]
        command += ["--serial"] if serial else []
        child = subprocess.Popen(
            command,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            env=environment,
            start_new_session=True,  # its own process group: its workers end with it
        )
        try:
            stdout, stderr = child.communicate(timeout=timeout)
        except subprocess.TimeoutExpired:
            raise KintinuousError(
                f"the warm-up from an empty cache took over {timeout:.0f} s; it was stopped"
            ) from None
        finally:
            end_process_group(child)
    if child.returncode != 0:
        lines = stderr.strip().splitlines() or ["no output"]
        raise KintinuousError(f"the warm-up from an empty cache failed: {lines[-1]}")
    report = json.loads(stdout.strip().splitlines()[-1])
    if not serial:  # what a fresh installation's compile takes here, kept for the next one
        part = COMPILE_MAPPING if odometry == GROUNDTRUTH else COMPILE_ALL
        load_backend(backend).record_compile_seconds(part, report["seconds"])
    return report


def end_process_group(child: subprocess.Popen, grace: float = 5.0) -> None:
    """End `child` (started with start_new_session) and every process of its group: SIGTERM,
    then SIGKILL to those left after `grace` seconds; return once none is left. Further
    signals wait until then, so that a second Ctrl-C cannot leave the group half ended."""
    ending = {signal.SIGINT, signal.SIGTERM, signal.SIGHUP}
    blocked = signal.pthread_sigmask(signal.SIG_BLOCK, ending)
    try:
        for number in (signal.SIGTERM, signal.SIGKILL):
            with contextlib.suppress(ProcessLookupError):
                os.killpg(child.pid, number)
            with contextlib.suppress(subprocess.TimeoutExpired):
                child.wait(timeout=grace)
            if _group_ended(child.pid, grace):
                break
        child.wait()
        for stream in (child.stdout, child.stderr):
            if stream is not None:
                stream.close()
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, blocked)


def _group_ended(group: int, wait: float) -> bool:
    """Whether process group `group` has no live process, polling for up to `wait` seconds.
    A zombie (dead, not yet reaped by whoever inherited it) counts as ended."""
    deadline = time.monotonic() + wait
    while _live_members(group):
        if time.monotonic() >= deadline:
            return False
        time.sleep(0.05)
    return True


def _live_members(group: int) -> list[int]:
    """Pids of the processes of group `group` that are not zombies (from /proc)."""
    members = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rpartition(")")[2].split()
        except OSError:  # ended while we looked
            continue
        if len(fields) > 2 and int(fields[2]) == group and fields[0] not in ("Z", "X"):
            members.append(int(stat.parent.name))
    return members


def format_report(report: dict[str, Any], kernels: int = 10) -> str:
    """Per-stage seconds, which add up to the whole wait (the rest: loading, setting up the
    warm-up's frames), then the `kernels` slowest compilations."""
    stages = dict(report["stage_seconds"])
    stages["rest"] = max(0.0, report["seconds"] - sum(stages.values()))
    lines = [
        f"{report['backend']} backend ready in {report['seconds']:.1f} s "
        f"(odometry: {', '.join(report['methods'])})",
        f"{'stage':12s} {'seconds':>8s}",
    ]
    lines += [f"{stage:12s} {value:8.1f}" for stage, value in stages.items()]
    compiled = report["kernel_seconds"]
    if compiled:
        total = sum(compiled.values())
        lines.append(f"compiled {len(compiled)} kernels ({total:.1f} s of compiling); the slowest:")
        slowest = list(compiled.items())[:kernels]
        lines += [f"  {seconds:6.1f} s  {name}" for name, seconds in slowest]
    else:
        lines.append("nothing compiled: every kernel came from numba's cache")
    return "\n".join(lines)
