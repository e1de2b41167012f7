"""`kintinuous warmup` and the wait before a run's progress bar: what numba compiles is seen
through its compile events, and a warmed-up backend compiles nothing more."""

import json
import os
import subprocess
import sys
from pathlib import Path

import numba
import pytest

from kintinuous_ref.backend import load_backend
from kintinuous_ref.config import Config
from kintinuous_ref.program import warmup
from kintinuous_ref.program.cli import main

TINY = Path(__file__).resolve().parents[1] / "data" / "tiny_desk"


def test_compile_events_time_each_compilation_once():
    @numba.njit
    def triple(x):
        return 3 * x

    with warmup.compile_events() as compiled:
        assert triple(2) == 6
        assert triple(5) == 15  # same types: no second compilation
    (name,) = compiled
    assert name.endswith("triple") and compiled[name] > 0
    with warmup.compile_events() as again:
        triple(7)
    assert again == {}


def test_after_a_warm_up_a_run_compiles_nothing():
    backend = load_backend("cpu")
    first = warmup.warm_up(backend, Config(), "icp")
    assert first.methods == ["icp"]
    assert set(first.stage_seconds) >= {"preprocess", "odometry", "integrate", "raycast"}
    second = warmup.warm_up(backend, Config(), "icp")
    assert second.kernel_seconds == {}
    assert second.seconds < 30


def test_warmup_command_reports_stages_and_kernels(capsys):
    assert main(["warmup", "--backend", "cpu", "--odometry", "groundtruth", "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["backend"] == "cpu" and report["methods"] == ["groundtruth"]
    assert "odometry" in report["stage_seconds"] and report["seconds"] > 0


def test_the_empty_cache_measurement_runs_in_its_own_process():
    """On the reference (nothing to compile) the child's report comes back whole."""
    report = warmup.warm_up_from_empty_cache("ref", "groundtruth", serial=True, timeout=300)
    assert report["backend"] == "ref" and report["kernel_seconds"] == {}
    assert report["methods"] == ["groundtruth"]


def test_unknown_odometry_is_one_line():
    with pytest.raises(SystemExit):
        main(["warmup", "--odometry", "kinfu"])


@pytest.mark.parametrize("cached", [False, True])
def test_reconstruct_prepares_the_kernels_before_its_progress_bar(
    tmp_path, capsys, monkeypatch, cached
):
    """The warm-up runs before the bar; a cold cache is announced, a warm one is not."""
    import sys

    from kintinuous_fast.backend import FastBackend
    from kintinuous_ref.program import reconstruct

    def spy(*args, **kwargs):
        print("WARM-UP", file=sys.stderr)
        return warmup.warm_up(*args, **kwargs)

    monkeypatch.setattr(reconstruct, "_PREPARED", set())
    monkeypatch.setattr(reconstruct, "warm_up", spy)
    monkeypatch.setattr(FastBackend, "kernels_cached", lambda self, tracking=True: cached)
    options = ["--backend", "cpu", "--odometry", "icp", "--frames", "2", "--resolution", "32"]
    assert main(["reconstruct", str(TINY), *options, "--out", str(tmp_path / "run")]) == 0
    err = capsys.readouterr().err
    assert err.index("WARM-UP") < err.index("reconstruct:")  # the bar starts after the wait
    if cached:
        assert "compiling" not in err
    else:
        assert err.index("compiling the cpu kernels for mapping") < err.index("WARM-UP")


def test_two_processes_compile_the_model_and_the_tracking_apart():
    """The plumbing on the reference (nothing to compile, seconds): the model half, tracked by
    the reference, and the tracking half, on the reference's model, both run to the end."""
    assert warmup.compile_in_two_processes("ref", Config(), ["icp+rgbd"]) == {}


def test_each_half_compiles_the_types_of_a_whole_run(tmp_path):
    """Two children compile into an empty cache; a whole cpu warm-up in a third process then
    loads every kernel from it and compiles none (a half that fed a fast stage another type
    than a real run does would leave that kernel to compile again)."""
    script = (
        "import json, sys\n"
        "from kintinuous_ref.backend import load_backend\n"
        "from kintinuous_ref.config import Config\n"
        "from kintinuous_ref.program import warmup\n"
        "if __name__ == '__main__':\n"
        "    warmup.compile_in_two_processes('cpu', Config(), ['icp+rgbd'])\n"
        "    backend = load_backend('cpu')\n"
        "    report = warmup.warm_up(backend, Config(), 'icp+rgbd', parallel=False)\n"
        "    print(json.dumps([backend.kernels_cached(), report.kernel_seconds]))\n"
    )
    environment = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path)}
    done = subprocess.run(
        [sys.executable, "-c", script], capture_output=True, text=True, env=environment
    )
    assert done.returncode == 0, done.stderr[-2000:]
    cached, compiled_after = json.loads(done.stdout.strip().splitlines()[-1])
    assert cached and compiled_after == {}


def test_a_warm_cache_is_never_compiled_again_in_other_processes():
    backend = load_backend("cpu")
    warmup.warm_up(backend, Config(), "icp")
    assert backend.kernels_cached()  # the index of the raycast loop is on disk now
    assert load_backend("ref").kernels_cached()


def test_kernels_cached_from_other_sources_are_dropped(tmp_path):
    """A stamp of the package's sources in each cache folder: a folder stamped with other
    sources loses its cached kernels (and only those files) and is stamped anew; a folder
    stamped with these sources, and a second call, drop nothing."""
    from kintinuous_fast.targets import cache

    sources = tmp_path / "package"
    (sources / "stage").mkdir(parents=True)
    ops = sources / "stage" / "ops.py"
    ops.write_text("x = 1\n")
    before = cache.sources_stamp(sources)
    ops.write_text("x = 22\n")  # an edit: another size (and time)
    after = cache.sources_stamp(sources)
    assert before != after

    stale, fresh = tmp_path / "stale", tmp_path / "fresh"
    for folder, stamp in ((stale, before), (fresh, after)):
        folder.mkdir()
        for name in ("cpu._loop-12.py311.nbi", "cpu._loop-12.py311.1.nbc", "keep.txt"):
            (folder / name).write_text("-")
        (folder / cache.STAMP_NAME).write_text(stamp)
    assert cache.drop_stale_kernels([stale, fresh], after) == 2
    assert sorted(path.name for path in stale.iterdir()) == sorted([cache.STAMP_NAME, "keep.txt"])
    assert (stale / cache.STAMP_NAME).read_text() == after
    assert len(list(fresh.iterdir())) == 4
    assert cache.drop_stale_kernels([stale, fresh], after) == 0


def test_the_cache_stamp_matches_these_sources_after_loading_the_cpu_backend():
    from kintinuous_fast.targets import cache

    load_backend("cpu")
    for folder in cache.cache_folders():
        assert (folder / cache.STAMP_NAME).read_text() == cache.sources_stamp()


def test_the_stage_table_adds_up_to_the_wait():
    """A cold warm-up spends its time in the two compiling processes, and its stages then load
    their kernels: the table has a line for each, and the rest, so that it adds up."""
    report = {
        "backend": "cpu",
        "seconds": 38.8,
        "methods": ["icp"],
        "stage_seconds": {warmup.COMPILING: 36.2, "preprocess": 0.1, "odometry": 0.3},
        "kernel_seconds": {},
    }
    rows = warmup.format_report(report).splitlines()[2:-1]
    assert [row.split()[0] for row in rows] == [warmup.COMPILING, "preprocess", "odometry", "rest"]
    assert sum(float(row.split()[-1]) for row in rows) == pytest.approx(38.8, abs=0.1)
