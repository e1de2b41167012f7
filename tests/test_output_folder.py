"""One run per output folder, outputs that appear whole, and `table` under reconstruct's rule.

The concurrency case runs two real `kintinuous reconstruct` processes (data/tiny_desk, a 32^3
volume, ground-truth poses, the ref backend) into one folder: the first is paused (SIGSTOP) once
it holds the folder, so that the second always meets it alive, then let go. A SIGKILLed holder is
a helper process that takes the lock and is killed. The other cases run the command in this
process. docs/reliability.md lists these cases.
"""

import json
import os
import re
import shutil
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import cv2
import pytest

from kintinuous_ref.program.cli import main
from kintinuous_ref.program.output_folder import LOCK_NAME, atomic, is_temporary, locked

TINY = Path(__file__).resolve().parent.parent / "data" / "tiny_desk"
SMALL = ["--backend", "ref", "--resolution", "32", "--volume-size", "2"]
QUICK = [*SMALL, "--odometry", "groundtruth"]


def _argv(out: Path, *extra: str) -> list[str]:
    return ["reconstruct", str(TINY), "--out", str(out), *QUICK, *extra]


def _process(argv: list[str], **options) -> subprocess.Popen:
    command = [sys.executable, "-m", "kintinuous_ref.program.cli", *argv]
    return subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, **options)


def _messages(stderr: str) -> list[str]:
    """The lines of stderr that are not the progress bar."""
    lines = [line for line in re.split(r"[\r\n]", stderr) if line.strip()]
    return [line for line in lines if not line.startswith(("reconstruct:", "saving"))]


def _wait_for_holder(lock: Path, pid: int, seconds: float = 60) -> None:
    """Until `lock` names `pid` as its holder."""
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        if lock.is_file() and lock.read_text().startswith(f"{pid} "):
            return
        time.sleep(0.01)
    raise AssertionError(f"{pid} never took {lock}")


def _assert_whole_run(out: Path, frames: int) -> None:
    """report.json, trajectory.txt, mesh.ply and preview.png of one run of `frames` frames, each
    complete and agreeing with the others; no temporary or lock left."""
    report = json.loads((out / "report.json").read_text())
    assert report["status"] == "completed" and report["frames"] == frames
    assert report["dataset"] == str(TINY)
    poses = [line for line in (out / "trajectory.txt").read_text().splitlines() if line[:1] != "#"]
    assert len(poses) == frames
    header = (out / "mesh.ply").read_bytes()[:300].decode("ascii", "replace")
    assert int(header.split("element vertex ")[1].split()[0]) == report["mesh"]["vertices"] > 0
    assert cv2.imread(str(out / "preview.png")) is not None
    assert not [p.name for p in out.rglob("*") if is_temporary(p.name) or p.suffix == ".part"]
    assert not (out / LOCK_NAME).exists()


def test_two_runs_into_one_folder_one_is_refused_the_other_is_whole(tmp_path):
    out = tmp_path / "out"
    first = _process([*_argv(out), "--frames", "6"])
    try:
        _wait_for_holder(out / LOCK_NAME, first.pid)
        first.send_signal(signal.SIGSTOP)  # alive and holding the folder while the second starts
        second = _process([*_argv(out), "--frames", "3"])
        _, stderr = second.communicate(timeout=120)
    finally:
        first.send_signal(signal.SIGCONT)
    _, first_stderr = first.communicate(timeout=180)
    assert first.returncode == 0, first_stderr.decode()
    assert second.returncode == 2
    messages = _messages(stderr.decode())
    assert len(messages) == 1 and "Traceback" not in stderr.decode()
    assert messages[0].startswith(f"kintinuous: error: {out}: in use by pid {first.pid} (")
    assert "kintinuous reconstruct" in messages[0] and "choose another --out" in messages[0]
    _assert_whole_run(out, 6)


HOLD = """
import sys, time
from kintinuous_ref.program.output_folder import locked
with locked(sys.argv[1]):
    print("held", flush=True)
    time.sleep(120)
"""


def _hold(folder: Path) -> subprocess.Popen:
    """A helper process holding `folder` (output_folder.locked), once it says so."""
    holder = subprocess.Popen(
        [sys.executable, "-c", HOLD, str(folder)], stdout=subprocess.PIPE, text=True
    )
    assert holder.stdout.readline() == "held\n"
    return holder


def test_a_sigkilled_holders_lock_does_not_block_the_next_run(tmp_path, capsys):
    out = tmp_path / "out"
    holder = _hold(out)
    try:
        refused = main(_argv(out, "--frames", "3"))
        error = capsys.readouterr().err
        assert refused == 2 and f"in use by pid {holder.pid}" in error
    finally:
        holder.kill()
        holder.wait()
    assert (out / LOCK_NAME).read_text().startswith(f"{holder.pid} ")  # stale: its file stays
    assert main(_argv(out, "--frames", "3")) == 0
    _assert_whole_run(out, 3)


def test_table_into_a_held_folder_is_refused(tmp_path, capsys):
    out = tmp_path / "table"
    holder = _hold(out)
    try:
        assert main(_table(out, _no_frames(tmp_path / "none"), "icp")) == 2
    finally:
        holder.kill()
        holder.wait()
    error = capsys.readouterr().err
    assert error.startswith(f"kintinuous: error: {out}: in use by pid {holder.pid} (")
    assert error.count("\n") == 1
    assert sorted(p.name for p in out.iterdir()) == [LOCK_NAME]  # nothing written


def test_synth_into_a_held_folder_is_refused_and_into_a_free_one_writes(tmp_path, capsys):
    out = tmp_path / "scene"
    synth = ["synth", "desk", "--out", str(out), "--frames", "1", "--width", "16", "--height", "12"]
    holder = _hold(out)
    try:
        assert main(synth) == 2
    finally:
        holder.kill()
        holder.wait()
    assert f"{out}: in use by pid {holder.pid} (" in capsys.readouterr().err
    assert main(synth) == 0  # the killed holder's lock file is no content to synth
    assert (out / "associations.txt").is_file() and not (out / LOCK_NAME).exists()


WAIT = """
import sys
from pathlib import Path
from kintinuous_ref.program.output_folder import waiting_lock
with waiting_lock(Path(sys.argv[1])):
    print("held", flush=True)
    sys.stdin.read()
"""


def test_a_scenario_is_rendered_by_one_run_while_the_others_wait(tmp_path, monkeypatch):
    # The first run (a helper holding the cache's lock for `desk`) renders; the second waits for
    # it, then finds the frames there and renders nothing.
    from kintinuous_ref.datasets import synthetic
    from kintinuous_ref.program.reconstruct import open_dataset

    monkeypatch.setenv("KINTINUOUS_CACHE", str(tmp_path))
    renders = []
    monkeypatch.setattr(synthetic, "write_scenario", lambda *a, **k: renders.append(a))
    first = subprocess.Popen(
        [sys.executable, "-c", WAIT, str(tmp_path / ".desk.lock")],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
    )
    opened = []
    try:
        assert first.stdout.readline() == "held\n"
        second = threading.Thread(
            target=lambda: opened.append(open_dataset("desk", frames_needed=1)), daemon=True
        )
        second.start()
        time.sleep(0.5)
        assert second.is_alive() and not opened  # waiting for the first
        shutil.copytree(TINY, tmp_path / "desk")  # what the first run rendered
        first.stdin.close()
        second.join(60)
    finally:
        first.kill()
        first.wait()
    assert len(opened) == 1 and len(opened[0]) == 10 and renders == []


@pytest.mark.parametrize("leftover", ["empty", "unfinished-slice"])
def test_a_killed_runs_empty_slices_folder_does_not_block_a_rerun(tmp_path, capsys, leftover):
    # What a SIGKILL leaves: slices/ with no finished slice, a temporary, a lock file.
    out = tmp_path / "out"
    (out / "slices").mkdir(parents=True)
    if leftover == "unfinished-slice":
        (out / "slices" / "tmpk1ll3d.part").write_bytes(b"ply\n")
    (out / ".mesh.partial-999999-0badc0de.ply").write_bytes(b"ply\n")
    (out / LOCK_NAME).write_text("999999 kintinuous reconstruct (killed)\n")
    assert main(_argv(out, "--frames", "3")) == 0, capsys.readouterr().err
    _assert_whole_run(out, 3)


def test_a_slices_folder_holding_a_slice_is_an_earlier_result(tmp_path, capsys):
    out = tmp_path / "out"
    (out / "slices").mkdir(parents=True)
    (out / "slices" / "slice_0000.ply").write_bytes(b"ply\n")
    assert main(_argv(out, "--frames", "3")) == 2
    error = capsys.readouterr().err
    assert error == (
        f"kintinuous: error: {out}: holds an earlier result (slices); pass --overwrite to replace "
        "it, or choose another --out\n"
    )
    assert sorted(p.name for p in out.iterdir()) == ["slices"]  # changed nothing


def _no_frames(folder: Path) -> str:
    """An empty folder: a dataset that exists, whose runs fail at once (a table of datasets
    none of which exists is refused before any run)."""
    folder.mkdir(parents=True)
    return str(folder)


def _table(out: Path, dataset: str, method: str, *extra: str) -> list[str]:
    return ["table", dataset, "--methods", method, "--out", str(out), *SMALL, *extra]


def test_table_refuses_a_used_folder_and_overwrite_leaves_no_old_run(tmp_path, capsys):
    # Datasets without frames: their runs fail at once, yet each writes its run folder and the
    # table, as a real run does.
    out = tmp_path / "table"
    assert main(_table(out, _no_frames(tmp_path / "first"), "icp")) == 1
    first = (out / "table.md").read_text()
    assert (out / "runs" / "first" / "icp" / "report.json").is_file()
    (out / "notes.txt").write_text("mine")
    capsys.readouterr()
    assert main(_table(out, _no_frames(tmp_path / "second"), "rgbd")) == 2
    assert capsys.readouterr().err == (
        f"kintinuous: error: {out}: holds an earlier result (table.md, table.json, "
        "fig4_ranking_median.png, fig5_ranking_max.png, trajectories.png, runs); pass "
        "--overwrite to replace it, or choose another --out\n"
    )
    assert (out / "table.md").read_text() == first
    assert main(_table(out, str(tmp_path / "second"), "rgbd", "--overwrite")) == 1
    runs = sorted(str(p.relative_to(out)) for p in (out / "runs").rglob("*"))
    assert runs == ["runs/second", "runs/second/rgbd", "runs/second/rgbd/report.json"]
    assert "--overwrite" in (out / "table.md").read_text()
    assert (out / "notes.txt").read_text() == "mine"  # not the table's: left alone
    assert (
        sorted(p.name for p in out.iterdir() if is_temporary(p.name) or p.name == LOCK_NAME) == []
    )


def test_table_refuses_a_folder_holding_other_files(tmp_path, tmp_path_factory, capsys):
    (tmp_path / "notes.txt").write_text("mine")
    dataset = _no_frames(tmp_path_factory.mktemp("datasets") / "none")
    assert main(_table(tmp_path, dataset, "icp")) == 2
    assert capsys.readouterr().err == (
        f"kintinuous: error: {tmp_path}: is not empty (notes.txt); pass --overwrite to write the "
        "table among its files, or choose another --out\n"
    )
    assert sorted(p.name for p in tmp_path.iterdir()) == ["notes.txt"]


def test_a_refused_run_leaves_no_folder_behind(tmp_path, capsys, monkeypatch):
    monkeypatch.setenv("KINTINUOUS_CACHE", str(tmp_path / "cache"))
    out = tmp_path / "new"
    assert main(["reconstruct", str(tmp_path / "missing"), "--out", str(out), *QUICK]) == 2
    assert "missing" in capsys.readouterr().err
    assert not out.exists()  # the lock made it, and took it away with the lock


def test_locked_is_reentrant_in_a_process(tmp_path):
    with locked(tmp_path / "out") as out, locked(out):
        assert (out / LOCK_NAME).read_text().startswith(f"{os.getpid()} ")
    assert not (tmp_path / "out").exists()


def test_atomic_writers_of_one_name_never_show_half_a_file(tmp_path):
    # Two writers of 1 MiB files under one name, and a reader: every read is one writer's whole
    # file. A writer that fails leaves the file before it and no temporary.
    path = tmp_path / "mesh.ply"
    sizes = {b"a": 1 << 20, b"b": (1 << 20) + 7}
    path.write_bytes(b"a" * sizes[b"a"])
    stop = threading.Event()

    def write(letter: bytes) -> None:
        while not stop.is_set():
            with atomic(path) as temporary:
                with open(temporary, "wb") as file:
                    for _ in range(16):
                        file.write(letter * (sizes[letter] // 16))
                    file.write(letter * (sizes[letter] % 16))

    writers = [threading.Thread(target=write, args=(letter,)) for letter in sizes]
    for writer in writers:
        writer.start()
    try:
        for _ in range(300):
            data = path.read_bytes()
            assert len(data) == sizes[data[:1]] and data.count(data[:1]) == len(data)
    finally:
        stop.set()
        for writer in writers:
            writer.join()
    before = path.read_bytes()
    with pytest.raises(OSError), atomic(path) as temporary:
        temporary.write_bytes(b"half")
        raise OSError("disk full")
    assert path.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["mesh.ply"]
