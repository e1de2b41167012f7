"""One evaluation run (one odometry method on one sequence) and the executors that run many.

`run_one` is a plain top-level function of a picklable `RunSpec`, so the same function goes to a
local process pool (concurrent.futures) or to a Dask cluster (through `run_on_worker`, which first
checks that the worker sees the dataset folder). It never raises for a bad run: a missing image,
a corrupt file or a crashing tracker become a `RunOutcome` with status "failed" and a one-line
reason, so that one bad run cannot stop a table of many.
"""

from __future__ import annotations

import multiprocessing
import time
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from kintinuous_ref.backend import load_backend
from kintinuous_ref.config import Config
from kintinuous_ref.errors import ConfigError, KintinuousError
from kintinuous_ref.program.output_folder import atomic, write_text_atomic
from kintinuous_ref.strict_json import dumps as strict_dumps

OK, FAILED = "ok", "failed"


@dataclass(frozen=True)
class RunSpec:
    """Everything one run needs; only plain values, so that it pickles to any worker."""

    dataset: str  # label used in the tables (scenario name or folder name)
    path: str  # TUM folder of the sequence (a worker must be able to read it)
    method: str  # one of kintinuous_ref.odometry.METHODS
    out: str  # the run's own folder: trajectory.txt, report.json
    config: Config
    start: int = 0
    frames: int | None = None  # None: to the end of the sequence
    size: tuple[int, int] | None = None  # (width, height) to resize the images to, or None
    backend: str = "ref"  # a kintinuous_ref.backend name ("ref" = kintinuous_ref itself)
    mesh: bool = False  # also extract mesh.ply (slow)


@dataclass
class RunOutcome:
    """What came back from one run: the numbers of Tables I-VI, or why there are none."""

    dataset: str
    method: str
    status: str  # OK or FAILED
    reason: str = ""  # one line when FAILED
    errors: dict[str, float | int | None] | None = None  # metrics.TrajectoryErrors.as_dict()
    tracker_ms: dict[str, float | None] | None = None  # Table V: avg, min, max, std
    pipeline_ms: dict[str, float | None] | None = None  # Table VI: the same for the whole frame
    frames: int = 0
    tracking_failures: int = 0
    timestamps: np.ndarray | None = None  # (N,) of the estimated trajectory
    poses: np.ndarray | None = None  # (N, 4, 4) camera-to-world
    seconds: float = 0.0  # wall time of the run
    out: str = ""
    extra: dict[str, Any] = field(default_factory=dict)


def run_folder_name(method: str) -> str:
    """Folder name of a method's run: 'fovis/icp' -> 'fovis_icp' (no '/' in a file name)."""
    return method.replace("/", "_")


def timing_statistics(milliseconds: Iterable[float]) -> dict[str, float | None]:
    """avg, min, max and (population) std dev of per-frame times, as in the paper's Tables V-VI
    (None for no frames)."""
    values = np.asarray(list(milliseconds), dtype=np.float64)
    if values.size == 0:
        return {"avg": None, "min": None, "max": None, "std": None}
    return {
        "avg": float(values.mean()),
        "min": float(values.min()),
        "max": float(values.max()),
        "std": float(values.std()),
    }


def run_one(spec: RunSpec) -> RunOutcome:
    """Run one method on one sequence, write its folder and return its numbers (never raises
    for a bad run: the outcome says FAILED and why)."""
    started = time.perf_counter()
    try:
        outcome = _run(spec)
    except KintinuousError as err:
        outcome = RunOutcome(spec.dataset, spec.method, FAILED, reason=_one_line(str(err)))
    except Exception as err:  # a crash in one tracker must not stop the other runs
        reason = _one_line(f"{type(err).__name__}: {err}")
        outcome = RunOutcome(spec.dataset, spec.method, FAILED, reason=reason)
    outcome.seconds = time.perf_counter() - started
    outcome.out = spec.out
    if outcome.status == FAILED:
        write_failure(spec, outcome)
    return outcome


def _run(spec: RunSpec) -> RunOutcome:
    from kintinuous_ref import metrics, pipeline
    from kintinuous_ref.datasets import tum
    from kintinuous_ref.program.reconstruct import check_start

    sequence = tum.open_sequence(Path(spec.path))
    if sequence.groundtruth is None:
        raise ConfigError(f"{spec.path}: no groundtruth.txt, so no error can be measured")
    check_start(spec.start, sequence)
    groundtruth = sequence.groundtruth_for_frames()
    camera, frames = sequence.camera, sequence.frames(spec.start, spec.frames)
    if spec.size is not None:
        camera, frames = camera.resized(*spec.size), _resized(frames, spec.size)
    result = pipeline.run(
        frames, camera, spec.config, spec.method, groundtruth, load_backend(spec.backend)
    )
    if result.interrupted:
        raise KeyboardInterrupt
    trajectory = result.trajectory
    bad = np.flatnonzero(~np.isfinite(trajectory.poses).all(axis=(1, 2)))
    if len(bad):
        raise KintinuousError(f"the tracker returned a non-finite pose at frame {bad[0]}")
    errors = metrics.evaluate(trajectory, sequence.groundtruth)
    # The first frame is placed at the ground truth, not tracked: Tables V-VI time tracked frames.
    outcome = RunOutcome(
        spec.dataset,
        spec.method,
        OK,
        errors=errors.as_dict(),
        tracker_ms=timing_statistics(result.timings_ms["odometry"][1:]),
        pipeline_ms=timing_statistics(result.timings_ms["total"][1:]),
        frames=result.frames,
        tracking_failures=result.tracking_failures,
        timestamps=trajectory.timestamps,
        poses=trajectory.poses,
    )
    _write_run(spec, outcome, result)
    return outcome


def _resized(frames: Iterator, size: tuple[int, int]) -> Iterator:
    """Frames scaled to `size`: colour by area averaging, depth by nearest neighbour (averaging
    would invent depths between a foreground edge and the background, and mix in zeros)."""
    import cv2

    for frame in frames:
        frame.colour = cv2.resize(frame.colour, size, interpolation=cv2.INTER_AREA)
        frame.depth = cv2.resize(frame.depth, size, interpolation=cv2.INTER_NEAREST)
        yield frame


def _write_run(spec: RunSpec, outcome: RunOutcome, result: Any) -> None:
    """trajectory.txt and report.json (and mesh.ply with spec.mesh) in the run's folder."""
    from kintinuous_ref.datasets.tum import write_trajectory
    from kintinuous_ref.program.reconstruct import write_outputs

    out = Path(spec.out)
    out.mkdir(parents=True, exist_ok=True)
    report = _report(spec, outcome)
    report["failure_reasons"] = result.failure_reasons[:50]
    report["timings_ms"] = result.timings_ms  # raw per-frame times of every stage
    if spec.mesh:  # the pipeline's own report (mesh, volume) with ours on top
        report = write_outputs(result, out, report, preview=False)
    with atomic(out / "trajectory.txt") as temporary:
        write_trajectory(temporary, result.trajectory)
    write_text_atomic(out / "report.json", strict_dumps(report, indent=1) + "\n")


def write_failure(spec: RunSpec, outcome: RunOutcome) -> None:
    """report.json of a failed run (status and reason), best effort."""
    try:
        out = Path(spec.out)
        out.mkdir(parents=True, exist_ok=True)
        write_text_atomic(
            out / "report.json", strict_dumps(_report(spec, outcome), indent=1) + "\n"
        )
    except OSError:
        pass  # the reason still reaches the table through the outcome


def _report(spec: RunSpec, outcome: RunOutcome) -> dict[str, Any]:
    return {
        "dataset": spec.dataset,
        "path": spec.path,
        "odometry": spec.method,
        "backend": spec.backend,
        "start": spec.start,
        "frames_requested": spec.frames,
        "size": list(spec.size) if spec.size else None,
        "status": outcome.status,
        "reason": outcome.reason,
        "frames": outcome.frames,
        "tracking_failures": outcome.tracking_failures,
        "errors": outcome.errors,
        "tracker_ms": outcome.tracker_ms,
        "pipeline_ms": outcome.pipeline_ms,
    }


def _one_line(text: str) -> str:
    return " ".join(text.split()) or "unknown error"


# ----------------------------------------------------------------------------------------------
# Executors: the same run_one on local processes or on a Dask cluster.


def check_jobs(jobs: int) -> None:
    """Refuse fewer than one process (ConfigError naming --jobs)."""
    if jobs < 1:
        raise ConfigError(f"--jobs must be at least 1, got {jobs}")


def execute(
    specs: list[RunSpec],
    jobs: int = 1,
    scheduler: str | None = None,
    on_done: Callable[[RunOutcome, int, int], None] | None = None,
) -> list[RunOutcome]:
    """Run every spec and return the outcomes in the order of `specs`.

    jobs == 1 and no scheduler: in this process, one after the other. jobs > 1: a
    ProcessPoolExecutor of `jobs` processes on this machine. scheduler: the address of a running
    dask.distributed scheduler ("tcp://host:8786"), whose workers must see the same dataset paths
    and output folder (relative ones are made absolute here first). `on_done(outcome, finished,
    total)` is called as each run finishes.
    """
    check_jobs(jobs)
    if scheduler is not None:
        finished = _on_dask(specs, scheduler)
    elif jobs == 1 or len(specs) <= 1:
        finished = ((i, run_one(spec)) for i, spec in enumerate(specs))
    else:
        finished = _on_processes(specs, jobs)
    outcomes: list[RunOutcome | None] = [None] * len(specs)
    for count, (index, outcome) in enumerate(finished, start=1):
        outcomes[index] = outcome
        if on_done is not None:
            on_done(outcome, count, len(specs))
    return outcomes  # type: ignore[return-value]  (every index was filled)


def _on_processes(specs: list[RunSpec], jobs: int) -> Iterator[tuple[int, RunOutcome]]:
    # "spawn": fresh interpreters, safe whatever threads (numba, OpenCV) the parent has started.
    context = multiprocessing.get_context("spawn")
    pool = ProcessPoolExecutor(max_workers=min(jobs, len(specs)), mp_context=context)
    try:
        futures = {pool.submit(run_one, spec): i for i, spec in enumerate(specs)}
        for future in as_completed(futures):
            yield futures[future], _result_or_failure(future, specs[futures[future]])
    finally:
        # On Ctrl-C (or any error here) the runs not yet started are dropped, not waited for.
        pool.shutdown(wait=True, cancel_futures=True)


def dask_client(scheduler: str) -> Any:
    """A dask.distributed Client connected to `scheduler`; a one-line error without dask."""
    try:
        from dask.distributed import Client
    except ImportError:
        raise ConfigError(
            "--scheduler needs dask.distributed, which is not installed: "
            "pip install 'kintinuous[dask]'"
        ) from None
    try:
        return Client(scheduler, timeout="20s")
    except (OSError, TimeoutError) as err:
        raise ConfigError(f"cannot reach the Dask scheduler at {scheduler}: {err}") from None


def _on_dask(specs: list[RunSpec], scheduler: str) -> Iterator[tuple[int, RunOutcome]]:
    from dask.distributed import as_completed as dask_completed

    # A worker runs in a folder of its own: a relative path means the client's folder.
    specs = [
        replace(spec, path=str(Path(spec.path).absolute()), out=str(Path(spec.out).absolute()))
        for spec in specs
    ]
    client = dask_client(scheduler)
    try:
        # pure=False: two identical specs are still two runs (timings differ between them).
        futures = client.map(run_on_worker, specs, pure=False)
        index = {future.key: i for i, future in enumerate(futures)}
        for future in dask_completed(futures):
            i = index[future.key]
            yield i, _result_or_failure(future, specs[i])
    finally:
        client.close()


def run_on_worker(spec: RunSpec) -> RunOutcome:
    """run_one on a Dask worker. The client opened the dataset to plan the runs, so a folder that
    this worker cannot see is a failed run whose reason names the worker and the path: on a
    cluster that is a file system mounted elsewhere or not at all, not a missing dataset."""
    if Path(spec.path).is_dir():
        return run_one(spec)
    from distributed import get_worker

    reason = (
        f"worker {get_worker().address} cannot see the dataset folder {spec.path} "
        "(every worker needs the datasets at the client's paths)"
    )
    outcome = RunOutcome(spec.dataset, spec.method, FAILED, reason=reason, out=spec.out)
    write_failure(spec, outcome)
    return outcome


def _result_or_failure(future: Any, spec: RunSpec) -> RunOutcome:
    """The future's outcome; a worker that died (out of memory, killed) is a failed run."""
    try:
        return future.result()
    except Exception as err:
        reason = _one_line(f"worker failed: {type(err).__name__}: {err}")
        return RunOutcome(spec.dataset, spec.method, FAILED, reason=reason, out=spec.out)
