"""`kintinuous course DIR`: the lessons of notebooks/ as notebooks with their outputs.

The lessons are stored as jupytext percent-format `.py` files, so that their diffs stay
readable; Jupyter without the jupytext extension shows them as scripts, and nobody sees a figure
before running them. This converts each lesson to an `.ipynb` in DIR, executes it there in a
fresh kernel of this interpreter (the environment tests/test_notebooks.py checks them in), and
renders it to an HTML page with its figures embedded, which any browser opens. The tests build
the course through build_course, so that CI runs each lesson once, as a student does.

The lessons ship with the source, not in the wheel: they are found beside the package (an
editable install), in the current folder or one above it (a source checkout), or in the folder
given with --notebooks.
"""

from __future__ import annotations

import asyncio
import os
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from threading import Event, Lock
from typing import TYPE_CHECKING, Any

from kintinuous_ref.datasets import DATA_VARIABLE
from kintinuous_ref.errors import KintinuousError
from kintinuous_ref.signals import Interrupted

if TYPE_CHECKING:
    from nbformat import NotebookNode

LESSON_PATTERN = "[0-9][0-9]_*.py"
# Per cell: the slowest cell of a lesson takes seconds once the numba kernels are compiled, and
# under a minute while the first lesson compiles them; a hang still ends.
CELL_TIMEOUT_S = 600
NEEDED_MODULES = ("jupytext", "nbclient", "nbconvert", "ipykernel")
MAX_DEFAULT_JOBS = 4


@dataclass
class LessonResult:
    """One lesson built: where its notebook and page are, how long it ran, why it failed."""

    name: str
    seconds: float
    notebook: Path
    html: Path | None
    error: str | None = None  # one line naming the failing cell; None when every cell ran

    @property
    def ok(self) -> bool:
        return self.error is None


def find_notebooks(folder: Path | None = None) -> Path:
    """The folder holding the lessons: `folder` if given, else notebooks/ beside the package (an
    editable install) or in the current folder or one above it (a source checkout)."""
    if folder is not None:
        if not _holds_lessons(folder):
            raise KintinuousError(f"{folder}: no lessons (NN_name.py files) in this folder")
        return folder
    package_checkout = Path(__file__).resolve().parents[2]
    here = Path.cwd().resolve()
    for root in (package_checkout, here, *here.parents):
        if _holds_lessons(root / "notebooks"):
            return root / "notebooks"
    raise KintinuousError(
        "the lessons (notebooks/*.py) are not in the installed package, they come with the "
        "source: run `kintinuous course DIR` inside a source checkout of kintinuous, or name "
        "its notebooks folder with --notebooks FOLDER"
    )


def _holds_lessons(folder: Path) -> bool:
    return folder.is_dir() and any(folder.glob(LESSON_PATTERN))


def select_lessons(notebooks: Path, wanted: Sequence[str] | None = None) -> list[Path]:
    """The lesson files in course order; `wanted` picks some by number ("03") or name."""
    paths = sorted(notebooks.glob(LESSON_PATTERN))
    if not wanted:
        return paths
    chosen = []
    for key in wanted:
        matches = [path for path in paths if key in (path.stem, path.stem[:2])]
        if not matches:
            names = ", ".join(path.stem for path in paths)
            raise KintinuousError(f"no lesson {key!r} in {notebooks} (the lessons: {names})")
        chosen += [path for path in matches if path not in chosen]
    return sorted(chosen)


def lesson_environment(notebooks: Path) -> dict[str, str]:
    """The kernel's environment: the one the tests check the lessons in (one numba thread for
    their small arrays, off-screen VTK, Agg standing for whatever backend a user has set, which
    the lessons' `%matplotlib inline` replaces), with the real data beside the source checkout
    the lessons were taken from."""
    env = dict(os.environ, PYVISTA_OFF_SCREEN="true", MPLBACKEND="Agg")
    env.setdefault("NUMBA_NUM_THREADS", "1")
    shared_data = notebooks.resolve().parent.parent / "shared" / "data"
    if shared_data.is_dir():
        env.setdefault(DATA_VARIABLE, str(shared_data))
    return env


def check_tools() -> None:
    """One line naming what to install when the notebook tools are missing."""
    import importlib.util

    missing = [name for name in NEEDED_MODULES if importlib.util.find_spec(name) is None]
    if missing:
        raise KintinuousError(
            f"kintinuous course needs {', '.join(missing)}: pip install {' '.join(missing)} "
            "(or reinstall kintinuous, which depends on them)"
        )


def build_course(
    out: Path,
    lessons: Sequence[str] | None = None,
    *,
    notebooks: Path | None = None,
    html: bool = True,
    timeout_s: float = CELL_TIMEOUT_S,
    progress: Callable[[str], None] | None = None,
    jobs: int = 1,
) -> list[LessonResult]:
    """Convert, execute and render the chosen lessons into `out`, `jobs` at a time (each kernel
    runs one numba thread, so a job per core costs no lesson its speed); a lesson that times
    code (`runs_alone`) runs after the others, by itself. Results come in course order; a
    lesson that fails is reported in its result and the others still run."""
    check_tools()
    folder = find_notebooks(notebooks)
    paths = select_lessons(folder, lessons)
    out.mkdir(parents=True, exist_ok=True)
    env = lesson_environment(folder)
    done: dict[Path, LessonResult] = {}
    ending = Event()  # a signal ends the course: the lessons it cut short are not results
    reporting = Lock()  # one lesson's lines at a time, each with its own count

    def build(path: Path) -> None:
        result = build_lesson(path, out, env, html=html, timeout_s=timeout_s)
        with reporting:
            if ending.is_set():
                return
            done[path] = result
            if progress is not None:
                progress(f"[{len(done)}/{len(paths)}] {lesson_line(result)}")
                if not result.ok:
                    progress(f"kintinuous: lesson {result.name} failed in {result.error}")

    together = [path for path in paths if jobs > 1 and not runs_alone(path)]
    if together:
        _build_together(together, build, jobs, out, ending)
    for path in paths:
        if path not in done:
            build(path)
    return [done[path] for path in paths]


def runs_alone(path: Path) -> bool:
    """Whether a lesson asks to run by itself (`kintinuous: runs_alone: true` in its jupytext
    header): one that times code, whose numbers another lesson beside it would slow."""
    import jupytext

    return bool(jupytext.read(path).metadata.get("kintinuous", {}).get("runs_alone", False))


# The kernels of the lessons running now, so that a signal can end them all (_end_kernels).
_RUNNING_KERNELS: set[Any] = set()


def _build_together(
    paths: list[Path], build: Callable[[Path], None], jobs: int, out: Path, ending: Event
) -> None:
    """build(path) of every path, `jobs` threads at a time. The signal that ends the command
    reaches the main thread only: there it sets `ending`, cancels the lessons not started, ends
    the kernels of those running (so that each thread's lesson fails at once) and is raised
    once every thread has stopped, with the lessons done kept in `out`."""
    from concurrent.futures import ThreadPoolExecutor, wait

    pool = ThreadPoolExecutor(max_workers=jobs, thread_name_prefix="lesson")
    futures = [pool.submit(build, path) for path in paths]
    try:
        wait(futures)
    except KeyboardInterrupt as signal_raised:
        ending.set()
        pool.shutdown(wait=False, cancel_futures=True)
        _end_kernels()
        name = getattr(signal_raised, "signal_name", "SIGINT")
        raise Interrupted(name, f"interrupted; the lessons done are in {out}") from signal_raised
    finally:
        pool.shutdown(wait=True)  # the lessons running end with their kernels
    for future in futures:
        future.result()  # an error of the course's own code, not a lesson's


def _end_kernels() -> None:
    """Kill the kernel processes of the lessons running now."""
    for kernel in list(_RUNNING_KERNELS):
        process = getattr(getattr(kernel, "provisioner", None), "process", None)
        if process is not None and process.poll() is None:
            process.kill()


def build_lesson(
    path: Path, out: Path, env: dict[str, str], *, html: bool = True, timeout_s: float
) -> LessonResult:
    """One lesson: its notebook executed in `out` (kept with the outputs up to a failing cell,
    whose traceback is the student's best lead) and its HTML page."""
    import jupytext
    import nbformat

    notebook = jupytext.read(path)
    # a standalone notebook: the jupytext extension would otherwise pair it with a new .py
    notebook.metadata.pop("jupytext", None)
    started = time.perf_counter()
    error = execute(notebook, out, env, timeout_s)
    seconds = time.perf_counter() - started
    target = out / f"{path.stem}.ipynb"
    nbformat.write(notebook, target)
    page = write_html(notebook, out / f"{path.stem}.html") if html else None
    return LessonResult(path.stem, seconds, target, page, error)


def execute(
    notebook: NotebookNode, folder: Path, env: dict[str, str], timeout_s: float
) -> str | None:
    """Run every cell in a fresh kernel of this interpreter with `folder` as the working
    folder; None, or one line naming the failing cell and the error."""
    from nbclient import NotebookClient

    cells: list[int] = []
    kernel = this_interpreter_kernel()
    _RUNNING_KERNELS.add(kernel)
    client = NotebookClient(
        notebook,
        timeout=timeout_s,
        km=kernel,
        resources={"metadata": {"path": str(folder)}},
        on_cell_start=lambda cell, cell_index: cells.append(cell_index),
    )
    try:
        client.execute(env=env)
    except Exception as err:  # the lesson's own error (or a dead kernel): reported, not raised
        if cancelled(err):
            raise Interrupted("SIGINT", f"interrupted; the lessons done are in {folder}") from err
        return failure_line(notebook, cells[-1] if cells else None, err)
    finally:
        _RUNNING_KERNELS.discard(kernel)
        shut_down(kernel)
    return None


def shut_down(kernel: Any) -> None:
    """End a lesson's kernel with its lesson: nbclient leaves a kernel it was handed running,
    and a course would otherwise keep one process per lesson until it exits."""
    from nbclient.util import run_sync

    if kernel.has_kernel:
        run_sync(kernel.shutdown_kernel)(now=True)


def cancelled(err: BaseException) -> bool:
    """Whether a lesson's failure comes from a signal to this process: nbclient answers SIGINT
    and SIGTERM by shutting the kernel down, and the lesson then ends with a dead kernel, raised
    while its pending task was cancelled. Going on to the next lesson would ignore the signal."""
    cause: BaseException | None = err
    while cause is not None:
        if isinstance(cause, (asyncio.CancelledError, KeyboardInterrupt)):
            return True
        cause = cause.__cause__ or cause.__context__
    return False


def this_interpreter_kernel() -> Any:
    """A kernel manager whose `python3` kernel is this interpreter: a kernel spec installed for
    the user (another Python, perhaps without kintinuous) would otherwise win."""
    import zmq
    from ipykernel.kernelspec import get_kernel_dict
    from jupyter_client.kernelspec import KernelSpec, KernelSpecManager
    from jupyter_client.manager import AsyncKernelManager

    class ThisInterpreter(KernelSpecManager):
        def get_kernel_spec(self, kernel_name: str) -> KernelSpec:
            spec = get_kernel_dict()
            fields = ("argv", "display_name", "language", "metadata")
            return KernelSpec(resource_dir="", **{key: spec[key] for key in fields if key in spec})

    manager = AsyncKernelManager(kernel_name="python3", kernel_spec_manager=ThisInterpreter())
    if manager.has_trait("transport_encryption") and zmq.has("curve"):
        # the kernel's TCP traffic encrypted (and no warning that it is not)
        manager.transport_encryption = "auto"
    return manager


def failure_line(notebook: NotebookNode, index: int | None, err: Exception) -> str:
    """The failing cell's number and first line, and the error's type and first line."""
    kind = getattr(err, "ename", None) or type(err).__name__
    message = getattr(err, "evalue", None)
    if message is None:
        message = str(err).strip().splitlines()[0] if str(err).strip() else ""
    if index is None:
        return f"{kind}: {message}"
    source = notebook.cells[index].source.strip().splitlines()
    first = source[0] if source else ""
    code_number = sum(cell.cell_type == "code" for cell in notebook.cells[: index + 1])
    return f"code cell {code_number} ({first}): {kind}: {message}"


def write_html(notebook: NotebookNode, target: Path) -> Path:
    """The executed notebook as one HTML file, its figures embedded as data URIs."""
    from nbconvert import HTMLExporter

    exporter = HTMLExporter()
    exporter.embed_images = True
    body, _ = exporter.from_notebook_node(notebook, resources={"metadata": {"path": "."}})
    target.write_text(body, encoding="utf-8")
    return target


def figure_count(notebook: NotebookNode) -> int:
    """The pictures a notebook shows: its outputs holding a PNG."""
    return sum(
        "image/png" in output.get("data", {})
        for cell in notebook.cells
        if cell.cell_type == "code"
        for output in cell.get("outputs", [])
    )


def lesson_line(result: LessonResult) -> str:
    """One progress line: the lesson, its time, and its failure when it failed."""
    if result.ok:
        return f"{result.name}: {result.seconds:.1f} s"
    return f"{result.name}: FAILED after {result.seconds:.1f} s"


def default_jobs() -> int:
    """Lessons run at a time by default: one per core this process may use, at most
    MAX_DEFAULT_JOBS (each kernel holds its own arrays and compiled code in memory)."""
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    return max(1, min(MAX_DEFAULT_JOBS, cores or 1))


def run(
    out: Path,
    lessons: Sequence[str] | None,
    notebooks: Path | None,
    *,
    html: bool,
    jobs: int | None = None,
) -> int:
    """The command: progress and failures on stderr, a summary on stdout; 1 when a lesson
    failed. `jobs`: lessons at a time (default_jobs when None)."""
    started = time.perf_counter()
    results = build_course(
        out,
        lessons,
        notebooks=notebooks,
        html=html,
        progress=lambda line: print(line, file=sys.stderr, flush=True),
        jobs=default_jobs() if jobs is None else jobs,
    )
    failed = [result.name for result in results if not result.ok]
    kinds = ".ipynb and .html" if html else ".ipynb"
    print(
        f"{len(results) - len(failed)} of {len(results)} lessons ran in "
        f"{time.perf_counter() - started:.0f} s; wrote their {kinds} files to {out}"
        + (f"; failed: {', '.join(failed)}" if failed else "")
    )
    return 1 if failed else 0
