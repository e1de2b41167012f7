"""The first run's compile, told truthfully: a compile's wall time is kept beside numba's cache
and announced the next time those kernels compile; where none was measured, or its record
cannot be read, the range measured on the 2-core machine is given. A run that compiles says so
in one line, a run that loads everything from the cache says nothing about compiling.

No kernel is compiled here: a backend on the reference's stages stands for the cpu one, and the
compile workers' report of what they compiled is injected."""

import json
import stat

import pytest

from kintinuous_fast.targets import cache
from kintinuous_ref.backend import ReferenceBackend
from kintinuous_ref.config import Config
from kintinuous_ref.pipeline import GROUNDTRUTH
from kintinuous_ref.program import reconstruct, warmup


class CachingBackend(ReferenceBackend):
    """The reference's stages behind a cache that is warm or cold as the test says, keeping
    its compile times in `folder` as the cpu backend keeps them beside numba's cache."""

    name = "cached"

    def __init__(self, folder, cached=False):
        super().__init__()
        self.folder, self.cached = folder, cached

    def kernels_cached(self, tracking=True):
        return self.cached

    def compile_seconds(self, part):
        return cache.measured_compile_seconds(part, self.folder)

    def record_compile_seconds(self, part, seconds):
        cache.record_compile_seconds(part, seconds, self.folder)


@pytest.fixture
def compile_workers(monkeypatch):
    """The two compile workers, reporting that they compiled one kernel (without running)."""
    calls = []

    def compiled(backend_name, config, methods):
        calls.append(methods)
        return {"kintinuous_fast.tsdf.cpu.integrate": 1.5}

    monkeypatch.setattr(warmup, "compile_in_two_processes", compiled)
    monkeypatch.setattr(warmup.os, "cpu_count", lambda: 2)
    return calls


def compile_lines(text):
    return [line for line in text.splitlines() if "compil" in line]


def test_the_record_is_read_back_and_replaced_whole(tmp_path):
    assert cache.measured_compile_seconds("mapping", tmp_path) is None  # nothing yet
    cache.record_compile_seconds("mapping", 51.26, tmp_path)
    cache.record_compile_seconds("tracking", 78.0, tmp_path)
    assert cache.measured_compile_seconds("mapping", tmp_path) == 51.3
    assert cache.measured_compile_seconds("tracking", tmp_path) == 78.0
    path = tmp_path / cache.ESTIMATE_NAME
    assert json.loads(path.read_text()) == {"mapping": 51.3, "tracking": 78.0}
    assert stat.S_IMODE(path.stat().st_mode) == 0o644
    assert [p.name for p in tmp_path.iterdir()] == [cache.ESTIMATE_NAME]  # no temporary left


@pytest.mark.parametrize(
    "text",
    ["", "{not json", "[51.0]", '{"mapping": "fast"}', '{"mapping": -3}', '{"mapping": NaN}'],
)
def test_an_unreadable_record_says_nothing_is_known_and_is_replaced(tmp_path, text):
    (tmp_path / cache.ESTIMATE_NAME).write_text(text)
    assert cache.measured_compile_seconds("mapping", tmp_path) is None
    backend = CachingBackend(tmp_path)
    idle, busy = warmup.KNOWN_COMPILE_SECONDS["mapping"]
    assert warmup.compile_estimate(backend, "mapping") == (
        f"{idle}-{busy} s on 2 cores, idle to a load of 10; not yet measured here"
    )
    cache.record_compile_seconds("tracking", 20.0, tmp_path)
    assert cache.measured_compile_seconds("tracking", tmp_path) == 20.0


def test_a_folder_that_cannot_be_written_is_left_alone(tmp_path):
    folder = tmp_path / "file"
    folder.write_text("not a folder")
    cache.record_compile_seconds("mapping", 12.0, folder)  # no error
    assert cache.measured_compile_seconds("mapping", folder) is None


def test_the_cpu_backend_keeps_its_record_in_its_stage_cache_folder(tmp_path, monkeypatch):
    from kintinuous_fast.backend import FastBackend

    monkeypatch.setattr(cache, "stage_folders", lambda stages: {stages[0]: tmp_path})
    cpu = FastBackend("cpu")
    assert cpu.compile_seconds("tracking") is None
    cpu.record_compile_seconds("tracking", 33.3)
    assert cpu.compile_seconds("tracking") == 33.3
    assert cache.measured_compile_seconds("tracking", tmp_path) == 33.3
    cuda = FastBackend("cuda")  # compiles in every process: nothing to keep
    cuda.record_compile_seconds("tracking", 1.0)
    assert cuda.compile_seconds("tracking") is None


def test_which_kernels_a_run_still_compiles(tmp_path):
    class Partly(CachingBackend):
        def kernels_cached(self, tracking=True):
            return not tracking  # the mapping kernels are cached, the tracking ones are not

    assert warmup.kernels_to_compile(CachingBackend(tmp_path), True) == warmup.COMPILE_ALL
    assert warmup.kernels_to_compile(CachingBackend(tmp_path), False) == warmup.COMPILE_MAPPING
    assert warmup.kernels_to_compile(Partly(tmp_path), True) == warmup.COMPILE_TRACKING
    assert warmup.kernels_to_compile(Partly(tmp_path), False) is None
    assert warmup.kernels_to_compile(CachingBackend(tmp_path, cached=True), True) is None
    assert set(warmup.KNOWN_COMPILE_SECONDS) == set(warmup.COMPILE_PARTS)


def test_a_compile_is_measured_and_announced_the_next_time(
    tmp_path, monkeypatch, capsys, compile_workers
):
    """The first compile gives the range and ends with the seconds it took; those seconds are
    kept, and the next compile (a wiped cache) announces them; a warm cache says nothing."""
    monkeypatch.setattr(reconstruct, "_PREPARED", set())
    backend = CachingBackend(tmp_path)
    reconstruct.prepare_kernels(backend, Config(), GROUNDTRUTH)
    first = compile_lines(capsys.readouterr().err)
    assert len(first) == 1 and compile_workers == [[GROUNDTRUTH]]
    idle, busy = warmup.KNOWN_COMPILE_SECONDS["mapping"]
    assert first[0].startswith(
        f"compiling the cached kernels for mapping, not yet in numba's cache ({idle}-{busy} s on "
        "2 cores, idle to a load of 10; not yet measured here; later runs load them in "
        "seconds)... done in "
    )
    took = float(first[0].rsplit(" done in ", 1)[1].removesuffix(" s"))
    measured = backend.compile_seconds(warmup.COMPILE_MAPPING)
    assert measured is not None and abs(measured - took) <= 0.5  # the line's seconds, kept

    reconstruct._PREPARED.clear()  # a new process, after the cache was wiped
    reconstruct.prepare_kernels(backend, Config(), GROUNDTRUTH)
    second = compile_lines(capsys.readouterr().err)
    assert len(second) == 1 and second[0].startswith(
        f"compiling the cached kernels for mapping, not yet in numba's cache (about "
        f"{measured:.0f} s, as measured on this machine; later runs load them in seconds)..."
    )

    reconstruct._PREPARED.clear()
    backend.cached = True  # everything comes from the cache: the workers are not started
    reconstruct.prepare_kernels(backend, Config(), GROUNDTRUTH)
    assert compile_lines(capsys.readouterr().err) == []
    assert len(compile_workers) == 2


def test_a_warm_up_that_compiles_nothing_keeps_no_time(tmp_path, monkeypatch):
    """A cold cache whose kernels all load (a lost warm-up record) measured no compile: the
    record stays as it was."""
    monkeypatch.setattr(warmup, "compile_in_two_processes", lambda *args: {})
    monkeypatch.setattr(warmup.os, "cpu_count", lambda: 2)
    backend = CachingBackend(tmp_path)
    warmup.warm_up(backend, Config(), GROUNDTRUTH)
    assert not (tmp_path / cache.ESTIMATE_NAME).exists()


def test_an_error_during_the_compile_ends_the_notice_line(tmp_path, monkeypatch, capsys):
    def fails(*args):
        raise MemoryError("out of memory while compiling")

    monkeypatch.setattr(reconstruct, "_PREPARED", set())
    monkeypatch.setattr(warmup, "compile_in_two_processes", fails)
    monkeypatch.setattr(warmup.os, "cpu_count", lambda: 2)
    with pytest.raises(MemoryError):
        reconstruct.prepare_kernels(CachingBackend(tmp_path), Config(), "icp")
    err = capsys.readouterr().err
    assert err.endswith("later runs load them in seconds)...\n")
    idle, busy = warmup.KNOWN_COMPILE_SECONDS["mapping and tracking"]
    assert "for mapping and tracking" in err and f"({idle}-{busy} s on 2 cores" in err


@pytest.mark.parametrize(
    ("odometry", "serial", "part"),
    [("all", False, "mapping and tracking"), (GROUNDTRUTH, False, "mapping"), ("all", True, None)],
)
def test_warmup_from_an_empty_cache_keeps_its_time_for_this_installation(
    tmp_path, monkeypatch, odometry, serial, part
):
    """`warmup --empty-cache` measures a fresh installation's compile in a child process with a
    temporary cache; its wall time is kept in this installation's record (a serial one is not
    what a run pays, and is not kept). The child is replaced by its report."""
    backend = CachingBackend(tmp_path)
    report = {"backend": "cpu", "seconds": 61.25, "methods": [], "stage_seconds": {}}

    class Child:
        returncode, pid = 0, 0
        stdout = stderr = None

        def __init__(self, command, **options):
            assert options["env"]["NUMBA_CACHE_DIR"] != str(tmp_path)  # its own, empty

        def communicate(self, timeout=None):
            return "progress\n" + json.dumps(report) + "\n", ""

    monkeypatch.setattr(warmup.subprocess, "Popen", Child)
    monkeypatch.setattr(warmup, "end_process_group", lambda child: None)
    monkeypatch.setattr(warmup, "load_backend", lambda name: backend)
    assert warmup.warm_up_from_empty_cache("cpu", odometry, serial=serial) == report
    if part is None:
        assert not (tmp_path / cache.ESTIMATE_NAME).exists()
    else:
        assert backend.compile_seconds(part) == 61.2  # kept to a tenth of a second
        assert warmup.compile_estimate(backend, part) == "about 61 s, as measured on this machine"
