"""`kintinuous download`: archives made here from data/tiny_desk, served by http.server on
127.0.0.1 as a mirror of TUM's layout; checksums, corrupt archives and the cache."""

import functools
import hashlib
import http.server
import io
import tarfile
import threading
from pathlib import Path

import numpy as np
import pytest

from kintinuous_ref.camera import TUM_CAMERAS
from kintinuous_ref.datasets import download, tum
from kintinuous_ref.program import cli
from kintinuous_ref.program.cli import main

TINY = Path(__file__).resolve().parents[1] / "data" / "tiny_desk"
DESK = "freiburg1/rgbd_dataset_freiburg1_desk.tgz"
XYZ = "freiburg2/rgbd_dataset_freiburg2_xyz.tgz"
ROOM = "freiburg1/rgbd_dataset_freiburg1_room.tgz"


def tum_archive(top: str, camera: bool = True) -> bytes:
    """tiny_desk as TUM packs a sequence: one folder `top` in a gzipped tar."""
    buffer = io.BytesIO()
    with tarfile.open(fileobj=buffer, mode="w:gz") as tar:
        for item in sorted(TINY.rglob("*")):
            if item.is_file() and (camera or item.name != "intrinsics.json"):
                tar.add(item, arcname=f"{top}/{item.relative_to(TINY)}")
    return buffer.getvalue()


@pytest.fixture(scope="module")
def mirror(tmp_path_factory):
    """(base URL, served folder, sha256 per archive path) of a local mirror of TUM's layout."""
    root = tmp_path_factory.mktemp("mirror")
    archives = {
        DESK: tum_archive("rgbd_dataset_freiburg1_desk"),
        XYZ: tum_archive("rgbd_dataset_freiburg2_xyz", camera=False),
    }
    archives[ROOM] = archives[DESK][: len(archives[DESK]) // 2]  # truncated
    digests = {}
    for name, data in archives.items():
        (root / name).parent.mkdir(parents=True, exist_ok=True)
        (root / name).write_bytes(data)
        digests[name] = hashlib.sha256(data).hexdigest()

    class Quiet(http.server.SimpleHTTPRequestHandler):
        def log_message(self, *args):
            pass

    handler = functools.partial(Quiet, directory=str(root))
    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    yield f"http://127.0.0.1:{server.server_address[1]}/", root, digests
    server.shutdown()
    server.server_close()


@pytest.fixture
def cache(tmp_path, monkeypatch):
    monkeypatch.setenv("KINTINUOUS_CACHE", str(tmp_path / "cache"))
    monkeypatch.setenv("NO_PROXY", "127.0.0.1,localhost")
    monkeypatch.delenv("KINTINUOUS_MIRROR", raising=False)
    return tmp_path / "cache" / "tum"


def error_line(capsys):
    err = capsys.readouterr().err
    lines = [line for line in err.splitlines() if line.startswith("kintinuous:")]
    assert len(lines) == 1 and "Traceback" not in err, err
    return lines[0]


def leftovers(cache):
    """Every file or folder in the cache (nothing may be left by a refused download)."""
    return sorted(str(p.relative_to(cache)) for p in cache.rglob("*")) if cache.exists() else []


def test_known_names_are_tums_archives_and_the_help_lists_the_papers_four(capsys):
    assert download.SEQUENCES["fr1/desk"].archive == DESK
    url = download.TUM_BASE_URL + download.SEQUENCES["fr2/large_no_loop"].archive
    assert url == (
        "https://cvg.cit.tum.de/rgbd/dataset/freiburg2/rgbd_dataset_freiburg2_large_no_loop.tgz"
    )
    archive = download.SEQUENCES["fr3/long_office_household"].archive
    assert archive == "freiburg3/rgbd_dataset_freiburg3_long_office_household.tgz"
    assert download.SEQUENCES["fr2/desk"].camera == TUM_CAMERAS["freiburg2"]
    paper = tuple(name for name, known in download.SEQUENCES.items() if known.paper)
    others = tuple(name for name, known in download.SEQUENCES.items() if not known.paper)
    assert paper == cli.PAPER_SEQUENCES == ("fr1/desk", "fr2/desk", "fr1/room", "fr2/large_no_loop")
    assert others == cli.OTHER_SEQUENCES
    assert (cli.TUM_BASE_URL, cli.MIRROR_VARIABLE) == (
        download.TUM_BASE_URL,
        download.MIRROR_VARIABLE,
    )
    with pytest.raises(SystemExit):
        main(["download", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    for name in paper:
        assert name in text
    assert "not pinned" in text


@pytest.mark.slow
def test_download_by_name_from_a_mirror_then_reconstruct_by_name(mirror, cache, tmp_path, capsys):
    base, _, digests = mirror
    status = main(["download", "fr1/desk", "--mirror", base, "--sha256", digests[DESK]])
    assert status == 0
    assert digests[DESK] in capsys.readouterr().out
    assert leftovers(cache) == ["fr1", "fr1/desk"] + sorted(
        f"fr1/desk/{p.relative_to(TINY)}" for p in TINY.rglob("*")
    )
    # Downloading again finds it.
    assert main(["download", "fr1/desk", "--mirror", base]) == 0
    assert "already in" in capsys.readouterr().out

    # Reconstructing by name tracks exactly as from the folder it was packed from.
    common = ["--odometry", "icp+rgbd", "--backend", "cpu", "--resolution", "64", "--frames", "4"]
    assert main(["reconstruct", "fr1/desk", "--out", str(tmp_path / "named"), *common]) == 0
    assert main(["reconstruct", str(TINY), "--out", str(tmp_path / "folder"), *common]) == 0
    named = tum.read_trajectory(tmp_path / "named" / "trajectory.txt")
    folder = tum.read_trajectory(tmp_path / "folder" / "trajectory.txt")
    assert len(named) == 4
    np.testing.assert_allclose(named.poses, folder.poses, atol=1e-9)
    np.testing.assert_array_equal(named.timestamps, folder.timestamps)


def test_a_named_sequence_gets_its_tum_camera_and_the_mirror_variable_is_read(
    mirror, cache, monkeypatch
):
    from kintinuous_ref.program import reconstruct

    base, _, digests = mirror
    monkeypatch.setenv("KINTINUOUS_MIRROR", base)
    assert main(["download", "fr2/xyz", "--sha256", digests[XYZ]]) == 0
    sequence = reconstruct.open_dataset("fr2/xyz")
    assert sequence.camera == TUM_CAMERAS["freiburg2"]  # 520.9, 521.0, 325.1, 249.7
    assert len(sequence) == 10


def test_a_url_with_its_sha256_unpacks_under_the_archive_name(mirror, cache):
    from kintinuous_ref.program import reconstruct

    base, _, digests = mirror
    assert main(["download", base + DESK, "--sha256", digests[DESK]]) == 0
    sequence = reconstruct.open_dataset("rgbd_dataset_freiburg1_desk")
    assert sequence.path == cache / "rgbd_dataset_freiburg1_desk"
    np.testing.assert_array_equal(sequence[3].depth, tum.open_sequence(TINY)[3].depth)


def test_corrupt_archives_are_refused_with_one_line_and_nothing_kept(mirror, cache, capsys):
    base, _, digests = mirror
    wrong = "0" * 64
    assert main(["download", "fr1/desk", "--mirror", base, "--sha256", wrong]) == 2
    line = error_line(capsys)
    assert "rgbd_dataset_freiburg1_desk.tgz" in line and digests[DESK] in line and wrong in line
    assert leftovers(cache) == []

    # Truncated, no checksum to catch it: unpacking does.
    assert main(["download", "fr1/room", "--mirror", base]) == 2
    line = error_line(capsys)
    assert "rgbd_dataset_freiburg1_room.tgz" in line and "truncated or corrupt" in line
    assert leftovers(cache) == []

    # Truncated with the full archive's checksum: the checksum refuses it.
    assert main(["download", "fr1/room", "--mirror", base, "--sha256", digests[DESK]]) == 2
    assert "corrupt or truncated download" in error_line(capsys)
    assert leftovers(cache) == []

    # Not there at all; and an unknown name.
    assert main(["download", base + "nothing/here.tgz"]) == 2
    assert "404" in error_line(capsys)
    assert main(["download", "fr9/nowhere"]) == 2
    assert "fr1/desk" in error_line(capsys)  # the known names are listed
    assert main(["reconstruct", "fr1/room", "--out", str(cache.parent / "o")]) == 2
    assert "kintinuous download fr1/room" in error_line(capsys)
    assert not (cache / "fr1" / "room").exists()


def test_a_broken_download_resumes_where_it_stopped(cache, capsys):
    """The first response stops half way; the same command then asks for the rest only."""
    data = tum_archive("rgbd_dataset_freiburg1_xyz")
    half, asked = len(data) // 2, []

    class Flaky(http.server.BaseHTTPRequestHandler):
        def log_message(self, *args):
            pass

        def do_GET(self):
            ranged = self.headers.get("Range")
            asked.append(ranged)
            start = int(ranged.removeprefix("bytes=").rstrip("-")) if ranged else 0
            self.send_response(206 if ranged else 200)
            if ranged:
                self.send_header("Content-Range", f"bytes {start}-{len(data) - 1}/{len(data)}")
            self.send_header("Content-Length", str(len(data) - start))
            self.end_headers()
            cut = half if len(asked) == 1 else len(data)  # the first transfer breaks off
            self.wfile.write(data[start:cut])
            self.close_connection = True

    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), Flaky)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    try:
        url = f"http://127.0.0.1:{server.server_address[1]}/rgbd_dataset_freiburg1_xyz.tgz"
        digest = hashlib.sha256(data).hexdigest()
        assert main(["download", url, "--sha256", digest]) == 2
        assert f"{half} bytes kept, the same command resumes" in error_line(capsys)
        part = cache / download.PARTIAL / "rgbd_dataset_freiburg1_xyz.tgz"
        assert part.read_bytes() == data[:half]
        assert main(["download", url, "--sha256", digest]) == 0
    finally:
        server.shutdown()
        server.server_close()
    assert asked == [None, f"bytes={half}-"]  # the second transfer sent only the rest
    folder = cache / "rgbd_dataset_freiburg1_xyz"
    assert (folder / "associations.txt").read_bytes() == (TINY / "associations.txt").read_bytes()
    assert leftovers(cache) == sorted(
        str(p.relative_to(cache)) for p in [folder, *folder.rglob("*")]
    )  # no .partial left behind
