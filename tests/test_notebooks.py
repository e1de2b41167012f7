"""The course builds the README's way, and every lesson in it runs without an error.

The lessons are jupytext percent-format .py files (readable diffs). The module builds the course
once, with `kintinuous course`'s own function (kintinuous_ref.program.course.build_course), one
lesson per core as the command does: each lesson converted to an .ipynb in a temporary folder,
executed there by nbclient in a fresh kernel and rendered to HTML, so that CI runs each lesson
once, as a student does. The tests then read what it wrote. The numbers each notebook shows
are checked inside the notebook itself (assert cells against synthetic ground truth, and
np.testing.assert_allclose of kintinuous_fast against kintinuous_ref), so any error output fails
its lesson; on top, each must show at least two pictures, in the .ipynb and in its HTML page
(under MPLBACKEND=Agg, which would drop them if a notebook relied on the user's backend), and
end with a summary and exercises.
The lessons are the folder's numbered files (notebooks/[0-9][0-9]_*.py), in file order, which
is the reading order. Only the lessons whose tests are selected are built:
`pytest tests/test_notebooks.py -k 06` builds lesson 6 alone.
Budget: each lesson runs warm in well under 90 s on the 2-core machine (notebooks/README.md
lists the measured times and the load average they were measured under).
"""

from __future__ import annotations

import os
import re
import signal
import threading
import time
from pathlib import Path

import nbformat
import pytest

from kintinuous_ref.errors import KintinuousError
from kintinuous_ref.program import course
from kintinuous_ref.program.course import LessonResult, build_course, figure_count
from kintinuous_ref.signals import Interrupted

NOTEBOOKS = Path(__file__).resolve().parents[1] / "notebooks"
# Per-notebook limit: generous against a loaded machine, small enough that a hang is caught.
TIMEOUT_S = 240


def notebook_paths() -> list[Path]:
    return sorted(NOTEBOOKS.glob("[0-9][0-9]_*.py"))


def test_the_course_is_complete():
    """The lessons are the folder's numbered files, read in file order, and the course map in
    notebooks/README.md lists every one of them: a new lesson is picked up without editing this
    test, and one the map forgets fails it."""
    lessons = [path.stem for path in notebook_paths()]
    numbers = [name[:2] for name in lessons]
    assert lessons and len(set(numbers)) == len(numbers), f"two lessons share a number: {lessons}"
    course_map = (NOTEBOOKS / "README.md").read_text()
    for name in lessons:
        assert f"{name}.py" in course_map, f"notebooks/README.md does not list {name}"
    listed = [name for name in re.findall(r"`(\d\d_\w+)\.py`", course_map) if name in lessons]
    assert listed == sorted(listed), "notebooks/README.md lists the lessons out of file order"


@pytest.mark.parametrize("path", notebook_paths(), ids=lambda path: path.stem)
def test_lesson_ends_with_summary_and_exercises(path: Path):
    text = path.read_text()
    assert "# ## Summary" in text and "# ## Exercises" in text
    assert text.index("# ## Summary") < text.index("# ## Exercises")
    assert "check" in text[text.index("# ## Exercises") :].lower(), "exercises need a way to check"
    # Data come through the package (kintinuous_ref.datasets), never a machine's path: no string
    # literal starting at a root folder ("/name/...") or a drive ("X:\\...").
    absolute = re.search(r"""["'](/[A-Za-z_][\w.-]*/|[A-Za-z]:\\)""", text)
    assert absolute is None, f"{path.name} names an absolute path ({absolute.group(1)})"


def selected_lessons(request: pytest.FixtureRequest) -> list[str]:
    """The lessons of the tests pytest is about to run that need the built course."""
    return sorted(
        {
            item.callspec.params["lesson"]
            for item in request.session.items
            if "built_course" in getattr(item, "fixturenames", ())
            and Path(item.path) == Path(__file__)
        }
    )


@pytest.fixture(scope="module")
def built_course(request, tmp_path_factory) -> dict[str, LessonResult]:
    """The selected lessons built once into a temporary folder, as `kintinuous course` builds
    them; a hang is caught by the per-cell limit."""
    out = tmp_path_factory.mktemp("course")
    results = build_course(
        out,
        selected_lessons(request),
        notebooks=NOTEBOOKS,
        timeout_s=TIMEOUT_S,
        progress=print,
        jobs=course.default_jobs(),
    )
    return {result.name: result for result in results}


LESSON_IDS = [path.stem for path in notebook_paths()]


@pytest.mark.slow
@pytest.mark.parametrize("lesson", LESSON_IDS)
def test_lesson_runs_without_an_error(built_course, lesson: str):
    result = built_course[lesson]
    assert result.ok, f"{lesson} failed in {result.error}"
    notebook = nbformat.read(result.notebook, as_version=4)
    errors = [
        output
        for cell in notebook.cells
        if cell.cell_type == "code"
        for output in cell.get("outputs", [])
        if output.get("output_type") == "error"
    ]
    assert not errors, f"{lesson} shows an error: {errors[0].get('ename')}"
    warnings = [
        output["text"].strip().splitlines()[0]
        for cell in notebook.cells
        if cell.cell_type == "code"
        for output in cell.get("outputs", [])
        if output.get("output_type") == "stream" and output.get("name") == "stderr"
    ]
    assert not warnings, f"{lesson} writes to stderr (a warning the student sees): {warnings[0]}"
    assert result.seconds < TIMEOUT_S, f"{lesson} took {result.seconds:.0f} s"


@pytest.mark.slow
@pytest.mark.parametrize("lesson", LESSON_IDS)
def test_lesson_shows_its_figures_in_the_notebook_and_the_page(built_course, lesson: str):
    result = built_course[lesson]
    pictures = figure_count(nbformat.read(result.notebook, as_version=4))
    assert pictures >= 2, f"{lesson} showed {pictures} pictures"
    page = result.html.read_text(encoding="utf-8")
    embedded = page.count("data:image/png;base64,")
    assert embedded >= pictures, f"{lesson}.html embeds {embedded} of {pictures} pictures"


LESSON_WITH_A_FIGURE = """# %%
# %matplotlib inline
import matplotlib.pyplot as plt

plt.plot([0, 1])
"""

FAILING_LESSON = """# %%
x = 1

# %%
assert x == 2, "x is not two"
"""


def kernels_left() -> list[int]:
    """Process ids of this process's children that run a Jupyter kernel (read from /proc)."""
    children = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
            command = (stat.parent / "cmdline").read_bytes()
        except OSError:  # the process ended meanwhile
            continue
        if int(fields[1]) == os.getpid() and b"ipykernel" in command:
            children.append(int(stat.parent.name))
    return children


@pytest.mark.slow
def test_a_failing_lesson_is_named_with_its_cell_and_the_others_still_run(tmp_path, capsys):
    lessons = tmp_path / "notebooks"
    lessons.mkdir()
    (lessons / "01_fails.py").write_text(FAILING_LESSON)
    (lessons / "02_draws.py").write_text(LESSON_WITH_A_FIGURE)
    status = course.run(tmp_path / "out", None, lessons, html=True)
    assert status == 1
    stderr = capsys.readouterr().err
    assert (
        'lesson 01_fails failed in code cell 2 (assert x == 2, "x is not two"): '
        "AssertionError: x is not two"
    ) in stderr
    assert re.search(r"\[[12]/2\] 02_draws: ", stderr), stderr  # the lessons run side by side
    assert (tmp_path / "out" / "01_fails.ipynb").exists()  # its traceback, for the student
    assert kernels_left() == [], "a lesson's kernel outlived its lesson"
    drawn = nbformat.read(tmp_path / "out" / "02_draws.ipynb", as_version=4)
    assert figure_count(drawn) == 1
    assert "data:image/png;base64," in (tmp_path / "out" / "02_draws.html").read_text()


def test_lessons_not_found_says_what_would_work(tmp_path, monkeypatch):
    """An installed wheel holds no notebooks/: outside a checkout, one line names the ways."""
    monkeypatch.setattr(course, "__file__", str(tmp_path / "site" / "kintinuous_ref" / "x.py"))
    monkeypatch.chdir(tmp_path)
    with pytest.raises(KintinuousError, match="source checkout.*--notebooks FOLDER"):
        course.find_notebooks()


def test_lessons_are_chosen_by_number_or_name():
    chosen = course.select_lessons(NOTEBOOKS, ["05", "01_tsdf_fusion"])
    assert [path.stem for path in chosen] == ["01_tsdf_fusion", "05_icp"]
    with pytest.raises(KintinuousError, match="no lesson '99'"):
        course.select_lessons(NOTEBOOKS, ["99"])


# A lesson that records when it ran (its cell's output: start and end, seconds since the epoch).
TIMED_LESSON = """# %%
import time
started = time.time()
time.sleep({seconds})
print(started, time.time())
"""
RUNS_ALONE_HEADER = """# ---
# jupyter:
#   kintinuous:
#     runs_alone: true
# ---

"""


def ran_between(result: LessonResult) -> tuple[float, float]:
    """(start, end) that a TIMED_LESSON printed."""
    cell = nbformat.read(result.notebook, as_version=4).cells[0]
    started, ended = map(float, cell.outputs[0]["text"].split())
    return started, ended


@pytest.mark.slow
def test_lessons_run_two_at_a_time_and_a_timing_lesson_by_itself(tmp_path):
    lessons = tmp_path / "notebooks"
    lessons.mkdir()
    (lessons / "01_first.py").write_text(TIMED_LESSON.format(seconds=6))
    (lessons / "02_alone.py").write_text(RUNS_ALONE_HEADER + TIMED_LESSON.format(seconds=0))
    (lessons / "03_third.py").write_text(TIMED_LESSON.format(seconds=6))
    assert [course.runs_alone(path) for path in sorted(lessons.glob("*.py"))] == [0, 1, 0]
    results = build_course(tmp_path / "out", notebooks=lessons, html=False, jobs=2)
    assert [result.name for result in results] == ["01_first", "02_alone", "03_third"]
    assert all(result.ok for result in results)
    first, alone, third = (ran_between(result) for result in results)
    assert first[0] < third[1] and third[0] < first[1], "the two lessons did not overlap"
    assert alone[0] > max(first[1], third[1]), "the timing lesson ran beside another"


@pytest.mark.slow
def test_a_signal_ends_every_running_lesson_and_keeps_those_done(tmp_path):
    lessons = tmp_path / "notebooks"
    lessons.mkdir()
    (lessons / "01_quick.py").write_text(TIMED_LESSON.format(seconds=0))
    for name in ("02_long", "03_long", "04_never"):
        (lessons / f"{name}.py").write_text(TIMED_LESSON.format(seconds=120))

    def interrupt_once_both_long_lessons_run() -> None:
        deadline = time.monotonic() + 60
        while len(kernels_left()) < 2 or not (tmp_path / "out" / "01_quick.ipynb").exists():
            if time.monotonic() > deadline:
                return
            time.sleep(0.2)
        time.sleep(1)  # both kernels inside their cell
        os.kill(os.getpid(), signal.SIGINT)

    threading.Thread(target=interrupt_once_both_long_lessons_run, daemon=True).start()
    started = time.monotonic()
    with pytest.raises(Interrupted) as raised:
        build_course(tmp_path / "out", notebooks=lessons, html=False, jobs=2)
    assert raised.value.message == f"interrupted; the lessons done are in {tmp_path / 'out'}"
    assert time.monotonic() - started < 60, "the long lessons ran on after the signal"
    assert kernels_left() == [], "a lesson's kernel outlived the signal"
    assert (tmp_path / "out" / "01_quick.ipynb").exists()
    assert not (tmp_path / "out" / "04_never.ipynb").exists()
