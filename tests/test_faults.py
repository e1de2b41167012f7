"""Fault injection: the real `kintinuous reconstruct` in a subprocess (data/tiny_desk, a 32^3 or
64^3 volume, the ref backend) is stopped by signals at a given frame, meets a corrupt or
mis-sized frame late in the sequence, runs out of disk (RLIMIT_FSIZE) and is re-run into used
folders. However it ends, the work is kept: trajectory.txt, the mesh of what was fused and
report.json with its status, reason and last frame; no partial file stays; every message is one
line. docs/reliability.md lists these cases."""

import json
import re
import resource
import shutil
import signal
import subprocess
import sys
import textwrap
from pathlib import Path

import cv2
import numpy as np
import pytest

TINY = Path(__file__).resolve().parent.parent / "data" / "tiny_desk"
FRAMES = 10
SMALL = ["--backend", "ref", "--resolution", "32", "--volume-size", "2"]
# ~0.1-0.2 s a frame (ICP on the reference backend): a signal sent after frame 3 lands mid-run
SLOW = ["--backend", "ref", "--resolution", "64", "--volume-size", "2", "--odometry", "icp"]
PROGRESS = re.compile(r"\| *(\d+)/(\d+) \[")


def _command(out: Path, *extra: str, dataset: Path = TINY) -> list[str]:
    return [sys.executable, "-m", "kintinuous_ref.program.cli", "reconstruct", str(dataset)] + [
        "--out",
        str(out),
        *extra,
    ]


def _run(argv: list[str], **options) -> subprocess.CompletedProcess:
    return subprocess.run(argv, capture_output=True, text=True, timeout=180, **options)


def _last_line(stderr: str) -> str:
    """The message after the progress bar: the last line, which must be the only one that is
    not progress."""
    lines = [line for line in re.split(r"[\r\n]", stderr) if line.strip()]
    messages = [line for line in lines if not line.startswith(("reconstruct:", "rendering"))]
    assert "Traceback" not in stderr, stderr
    return messages[-1] if messages else ""


def _report(out: Path) -> dict:
    return json.loads((out / "report.json").read_text())


def _poses(out: Path) -> int:
    return sum(1 for line in (out / "trajectory.txt").read_text().splitlines() if line[:1] != "#")


def _vertices(out: Path) -> int:
    header = (out / "mesh.ply").read_bytes()[:300].decode("ascii", "replace")
    return int(header.split("element vertex ")[1].split()[0])


def _no_partial_files(out: Path) -> None:
    leftovers = [p.name for p in out.rglob("*") if ".part" in p.name or ".partial" in p.name]
    assert not leftovers, leftovers


def _stop_after(argv: list[str], frame: int, signals: list[int], second_after: str = "") -> tuple:
    """Run `argv`, send signals[0] once its progress shows `frame` frames done (and signals[1]
    once stderr shows `second_after`); (exit status, stderr)."""
    child = subprocess.Popen(argv, stderr=subprocess.PIPE, text=True, bufsize=0)
    seen, pending = "", list(signals)
    try:
        while pending:
            char = child.stderr.read(1)
            if not char:
                break
            seen += char
            done = PROGRESS.findall(seen)
            if len(pending) == len(signals) and done and int(done[-1][0]) >= frame:
                child.send_signal(pending.pop(0))
            elif len(pending) < len(signals) and second_after and second_after in seen:
                child.send_signal(pending.pop(0))
        rest = child.stderr.read()
        return child.wait(timeout=120), seen + rest
    finally:
        if child.poll() is None:
            child.kill()


@pytest.mark.parametrize(
    ("number", "status"),
    [(signal.SIGTERM, 143), (signal.SIGHUP, 129), (signal.SIGINT, 130)],
    ids=["SIGTERM", "SIGHUP", "SIGINT"],
)
def test_a_signal_at_frame_3_keeps_the_work(tmp_path, number, status):
    out = tmp_path / "out"
    code, stderr = _stop_after(_command(out, *SLOW), 3, [number])
    assert code == status, stderr
    report = _report(out)
    name = signal.Signals(number).name
    assert report["status"] == "interrupted" and report["reason"] == f"interrupted by {name}"
    assert report["interrupted"] is True
    done = report["frames"]
    assert 3 <= done < FRAMES and report["last_frame"] == done - 1
    assert _poses(out) == done
    assert _vertices(out) == report["mesh"]["vertices"] > 0
    assert f"writing the results of {done} frames (trajectory, mesh, report)..." in stderr
    assert _last_line(stderr) == (
        f"kintinuous: interrupted by {name} after frame {done - 1}: the {done} frames done are "
        f"saved in {out}"
    )
    _no_partial_files(out)


def test_a_second_signal_during_the_save_says_what_was_and_was_not_saved(tmp_path):
    # The save is made slow where it renders the preview (after trajectory.txt and mesh.ply).
    script = textwrap.dedent(
        """
        import sys, time
        from kintinuous_ref import mesh
        from kintinuous_ref.program import cli
        def render_preview(*args, **kw):
            sys.stderr.write("rendering\\n")  # one write: a signal cannot split it
            time.sleep(60)
        mesh.render_preview = render_preview
        sys.exit(cli.main(sys.argv[1:]))
        """
    )
    out = tmp_path / "out"
    argv = [sys.executable, "-c", script, *_command(out, *SLOW)[3:]]
    code, stderr = _stop_after(argv, 3, [signal.SIGINT, signal.SIGTERM], "rendering")
    assert code == 143, stderr
    assert re.fullmatch(
        rf"kintinuous: SIGTERM during the save: saved trajectory.txt, mesh.ply, "
        rf"volume_origins.txt, report.json in {re.escape(str(out))}; NOT saved: preview.png",
        _last_line(stderr),
    ), _last_line(stderr)
    assert sorted(p.name for p in out.iterdir()) == [
        "mesh.ply",
        "report.json",
        "slices",
        "trajectory.txt",
        "volume_origins.txt",
    ]
    report = _report(out)
    assert report["status"] == "interrupted"
    assert report["reason"] == "interrupted by SIGINT; SIGTERM during the save"
    assert report["not_saved"] == {"preview.png": "SIGTERM during the save"}
    assert _poses(out) == report["frames"] >= 3 and _vertices(out) > 0
    _no_partial_files(out)


@pytest.fixture
def broken_copy(tmp_path):
    """tiny_desk copied, with `damage(copy, frame)` applied to frame 7's images."""

    def make(damage) -> Path:
        copy = tmp_path / "seq"
        shutil.copytree(TINY, copy)
        damage(copy, 7)
        return copy

    return make


def _image(copy: Path, frame: int, kind: str) -> Path:
    line = (copy / "associations.txt").read_text().splitlines()
    rows = [row.split() for row in line if row and not row.startswith("#")]
    return copy / rows[frame][1 if kind == "rgb" else 3]


def _corrupt(copy: Path, frame: int) -> None:
    _image(copy, frame, "rgb").write_bytes(b"\x89PNG\r\n\x1a\n not really")


def _wrong_size(copy: Path, frame: int) -> None:
    path = _image(copy, frame, "depth")
    cv2.imwrite(str(path), np.zeros((60, 80), np.uint16))


@pytest.mark.parametrize(
    ("damage", "message"),
    [
        (_corrupt, "cannot read colour image"),
        (_wrong_size, "image is 80x60 but the camera is 160x120"),
    ],
    ids=["corrupt", "wrong-size"],
)
def test_a_bad_frame_late_stops_there_and_keeps_the_frames_before(
    tmp_path, broken_copy, damage, message
):
    copy = broken_copy(damage)
    out = tmp_path / "out"
    result = _run(_command(out, *SMALL, dataset=copy))
    assert result.returncode == 2, result.stderr
    bad = _image(copy, 7, "rgb" if damage is _corrupt else "depth")
    line = _last_line(result.stderr)
    assert line.startswith(f"kintinuous: error: frame 7: {bad}: ") and message in line
    assert line.endswith(f"the 7 frames done are saved in {out}")
    report = _report(out)
    assert report["status"] == "failed" and report["last_frame"] == 6 and report["frames"] == 7
    assert report["reason"].startswith(f"frame 7: {bad}")
    assert _poses(out) == 7 and _vertices(out) > 0
    _no_partial_files(out)


def test_skip_bad_frames_leaves_it_out_and_counts_it(tmp_path, broken_copy):
    copy = broken_copy(_corrupt)
    out = tmp_path / "out"
    result = _run(_command(out, *SMALL, "--skip-bad-frames", dataset=copy))
    assert result.returncode == 0, result.stderr
    report = _report(out)
    assert report["status"] == "completed" and report["frames"] == FRAMES - 1
    assert report["skipped_frames"] == 1
    assert report["skipped_reasons"][0].startswith(f"frame 7: {_image(copy, 7, 'rgb')}")
    assert _poses(out) == FRAMES - 1 and "skipped 1 bad" in result.stdout


def _limit_files(size: int):
    return lambda: resource.setrlimit(resource.RLIMIT_FSIZE, (size, size))


def test_a_full_disk_is_one_line_keeps_what_fits_and_leaves_no_partial_file(tmp_path):
    out = tmp_path / "out"
    result = _run(_command(out, *SMALL, "--odometry", "groundtruth"), preexec_fn=_limit_files(8000))
    assert result.returncode == 2, result.stderr
    line = _last_line(result.stderr)
    assert line.startswith("kintinuous: error: saved trajectory.txt, volume_origins.txt")
    assert "NOT slices: cannot write: File too large" in line
    report = _report(out)
    assert report["status"] == "completed" and report["frames"] == FRAMES
    assert set(report["not_saved"]) == {"slices", "mesh.ply"}
    assert _poses(out) == FRAMES and not (out / "mesh.ply").exists()
    _no_partial_files(out)


def test_an_unexpected_exception_is_one_line_a_crash_log_and_the_work_kept(tmp_path):
    script = textwrap.dedent(
        """
        import sys
        import kintinuous_ref.tsdf as tsdf
        from kintinuous_ref.program import cli
        real, calls = tsdf.integrate, []
        def integrate(*args, **kw):
            calls.append(1)
            if len(calls) == 9:
                raise ZeroDivisionError("injected")
            return real(*args, **kw)
        tsdf.integrate = integrate
        sys.exit(cli.main(sys.argv[1:]))
        """
    )
    out = tmp_path / "out"
    result = _run([sys.executable, "-c", script, *_command(out, *SMALL)[3:]])
    assert result.returncode == 70, result.stderr
    line = _last_line(result.stderr)
    assert line == (
        "kintinuous: internal error (a bug, please report it): "
        f"ZeroDivisionError: injected; traceback in {out / 'crash.log'}; the 8 frames done are "
        f"saved in {out}"
    )
    assert "ZeroDivisionError: injected" in (out / "crash.log").read_text()
    report = _report(out)
    assert report["status"] == "failed" and report["last_frame"] == 7 and _poses(out) == 8
    assert _vertices(out) > 0


def test_reruns_into_used_folders(tmp_path, broken_copy):
    out = tmp_path / "out"
    assert _run(_command(out, *SMALL, "--odometry", "groundtruth")).returncode == 0
    first = (out / "report.json").read_text()
    (out / "notes.txt").write_text("mine")
    # a second run is refused, before any work, and changes nothing
    refused = _run(_command(out, *SMALL))
    assert refused.returncode == 2
    assert _last_line(refused.stderr) == (
        f"kintinuous: error: {out}: holds an earlier result (report.json, trajectory.txt, "
        "mesh.ply, slices, preview.png, volume_origins.txt); pass --overwrite to replace it, "
        "or choose another --out"
    )
    assert (out / "report.json").read_text() == first
    # --overwrite into it with a run that fails at frame 7: only the new run's files remain
    copy = broken_copy(_corrupt)
    failed = _run(_command(out, *SMALL, "--overwrite", dataset=copy))
    assert failed.returncode == 2
    report = _report(out)
    assert report["status"] == "failed" and report["dataset"] == str(copy)
    assert report["odometry"] == "icp+rgbd" and _poses(out) == 7
    assert (out / "notes.txt").read_text() == "mine"  # not ours: left alone
    slices = sorted(p.name for p in (out / "slices").iterdir())
    assert len(slices) == report["slices"]


@pytest.mark.parametrize("kind", ["file", "empty", "proc"])
def test_an_output_that_cannot_be_a_folder(tmp_path, kind):
    target = {"file": tmp_path / "taken", "empty": "", "proc": "/proc/kintinuous-out"}[kind]
    if kind == "file":
        target.write_text("x")
    result = _run(_command(target, *SMALL))
    assert result.returncode == 2
    expected = {
        "file": f"kintinuous: error: {target}: exists and is not a folder; --out names a folder",
        "empty": "kintinuous: error: --out is empty: name an output folder",
        "proc": f"kintinuous: error: {target}: cannot write the output folder (",
    }[kind]
    assert _last_line(result.stderr).startswith(expected), result.stderr
    assert result.stderr.count("\n") <= 1 or kind == "proc"


def test_synth_larger_than_memory_is_one_line(tmp_path):
    # 60000x45000 images in a process allowed 3 GiB of address space: numpy's MemoryError, told
    # in one line with what to ask for instead; no frame written.
    def limit_memory():
        resource.setrlimit(resource.RLIMIT_AS, (3 << 30, 3 << 30))

    out = tmp_path / "big"
    argv = [sys.executable, "-m", "kintinuous_ref.program.cli", "synth", "desk", "--out", str(out)]
    argv += ["--frames", "1", "--width", "60000", "--height", "45000"]
    result = _run(argv, preexec_fn=limit_memory)
    assert result.returncode == 2, result.stderr
    assert "Traceback" not in result.stderr
    errors = [line for line in re.split(r"[\r\n]", result.stderr) if "kintinuous:" in line]
    assert errors == [
        "kintinuous: error: out of memory (ask for fewer or smaller frames, or a smaller volume)"
    ]
    assert not list(out.glob("rgb/*.png"))


def _synth(out: Path, **options) -> int:
    """Render 3 frames of `desk` at 160x120 into `out`; the frames this call rendered."""
    from kintinuous_ref.datasets import synthetic

    counts: list[int] = []
    synthetic.write_scenario(
        "desk", out, frames=3, width=160, height=120, on_rendering=counts.append, **options
    )
    return counts[0]


def test_a_render_stopped_while_it_makes_the_surface_lists_no_frames(tmp_path, monkeypatch):
    # the listings were written before scene.ply: a Ctrl-C while the surface was made left a
    # folder that listed its frames without it, which the cache took for complete ever after
    from kintinuous_ref.datasets import synthetic
    from kintinuous_ref.program.reconstruct import rendered_frames

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    out = tmp_path / "desk"
    with monkeypatch.context() as patch:
        patch.setattr(synthetic.Scenario, "surface_mesh", interrupted)
        with pytest.raises(KeyboardInterrupt):
            _synth(out)
    assert rendered_frames(out) == 0 and not (out / "scene.ply").exists()
    assert _synth(out) == 0  # the frames kept, the surface and the listings added
    assert rendered_frames(out) == 3 and (out / "scene.ply").is_file()
    assert not [p.name for p in out.rglob("*") if ".partial" in p.name]


def test_a_cached_scenario_without_its_surface_gets_it(tmp_path, monkeypatch):
    # a cache folder left listing its frames without scene.ply was never completed
    from kintinuous_ref.program.reconstruct import open_dataset, rendered_frames

    monkeypatch.setenv("KINTINUOUS_CACHE", str(tmp_path))
    open_dataset("desk", frames_needed=3)
    folder = tmp_path / "desk"
    (folder / "scene.ply").unlink()
    image = sorted((folder / "rgb").iterdir())[0]
    before = image.stat().st_mtime_ns
    open_dataset("desk", frames_needed=2)  # fewer than rendered: all 3 stay listed
    assert (folder / "scene.ply").is_file()
    assert rendered_frames(folder) == 3 and image.stat().st_mtime_ns == before


def test_synth_again_into_its_folder_says_it_rendered_nothing(tmp_path, capsys):
    # it printed "wrote 3 frames" again, having rendered none
    from kintinuous_ref.program import cli

    out = tmp_path / "desk"
    argv = ["synth", "desk", "--out", str(out), "--frames", "3", "--width", "160"]
    argv += ["--height", "120"]
    assert cli.main(argv) == 0
    assert capsys.readouterr().out.splitlines()[-1] == f"wrote 3 frames of 'desk' to {out}"
    assert cli.main(argv) == 0
    assert capsys.readouterr().out.splitlines()[-1] == (
        f"{out} already holds the 3 frames of 'desk': none rendered"
    )
    (out / "depth" / sorted(p.name for p in (out / "depth").iterdir())[1]).unlink()
    assert cli.main(argv) == 0
    assert capsys.readouterr().out.splitlines()[-1] == (
        f"wrote 1 frame of 'desk' to {out} (2 already there)"
    )
