"""TUM RGB-D sequences fetched by name (or any TUM-layout archive by URL) into the user cache.

`pooch` downloads (and checks the checksum) through a resumable fetch: the bytes that arrive are
kept in `.partial/ARCHIVE` under the cache, and a download that broke off asks only for the rest
the next time (an HTTP Range request; a server that ignores it sends the whole archive again).
The archive is unpacked into a temporary folder beside its destination and renamed into place
only when complete, so the cache never holds a half-unpacked sequence, and the archive is
deleted afterwards. A sequence known by
name gets an `intrinsics.json` with its TUM camera, so it opens like any TUM folder.

Checksums: the archives' sha256 values are not pinned here (None), as they could not be
computed from the published files when this table was written; `--sha256 HEX` pins one for a
download, and every download prints the sha256 of what it fetched so that it can be pinned.
"""

from __future__ import annotations

import re
import shutil
import tarfile
import tempfile
import zlib
from dataclasses import dataclass
from pathlib import Path

from kintinuous_ref.camera import TUM_CAMERAS, Intrinsics
from kintinuous_ref.errors import DatasetError
from kintinuous_ref.strict_json import dumps as strict_dumps

TUM_BASE_URL = "https://cvg.cit.tum.de/rgbd/dataset/"
MIRROR_VARIABLE = "KINTINUOUS_MIRROR"


@dataclass(frozen=True)
class KnownSequence:
    """A TUM RGB-D archive: its path under the dataset's base URL, camera and checksum."""

    archive: str  # e.g. freiburg1/rgbd_dataset_freiburg1_desk.tgz
    camera: Intrinsics
    sha256: str | None = None  # None: not pinned (see the module's note)
    paper: bool = False  # one of the four sequences of the paper's Table I


def _known(name: str, paper: bool = False) -> KnownSequence:
    camera, scene = name.split("/")
    folder = f"freiburg{camera[2]}"
    return KnownSequence(
        f"{folder}/rgbd_dataset_{folder}_{scene}.tgz", TUM_CAMERAS[folder], paper=paper
    )


SEQUENCES: dict[str, KnownSequence] = {
    "fr1/desk": _known("fr1/desk", paper=True),
    "fr2/desk": _known("fr2/desk", paper=True),
    "fr1/room": _known("fr1/room", paper=True),
    "fr2/large_no_loop": _known("fr2/large_no_loop", paper=True),
    "fr1/xyz": _known("fr1/xyz"),
    "fr1/360": _known("fr1/360"),
    "fr2/xyz": _known("fr2/xyz"),
    "fr3/long_office_household": _known("fr3/long_office_household"),
}


def cached(name: str, root: Path) -> Path | None:
    """The unpacked folder of a downloaded sequence (a known name or an archive's stem)."""
    if not re.fullmatch(r"[A-Za-z0-9_.-]+(/[A-Za-z0-9_.-]+)?", name) or ".." in name:
        return None
    folder = Path(root) / name
    return folder if folder.is_dir() else None


def _archive_stem(url: str) -> str:
    name = url.rstrip("/").rsplit("/", 1)[-1].split("?")[0]
    for suffix in (".tar.gz", ".tgz", ".tar.bz2", ".tar.xz", ".tar"):
        if name.endswith(suffix):
            return name[: -len(suffix)]
    raise DatasetError(f"{url}: not a tar archive (.tgz, .tar.gz, .tar.bz2, .tar.xz, .tar)")


PARTIAL = ".partial"  # under the cache root: archives whose download broke off


def resumable_fetch(part: Path, progress: bool = True):  # noqa: ANN201 - pooch's downloader
    """A pooch downloader that appends what arrives to `part` and, when `part` already holds the
    start of the archive, asks the server only for the rest."""

    def fetch(url: str, output_file: str, pooch_object: object) -> None:
        import urllib.error
        import urllib.request

        from tqdm import tqdm

        have = part.stat().st_size if part.is_file() else 0
        headers = {"Range": f"bytes={have}-"} if have else {}
        try:
            response = urllib.request.urlopen(
                urllib.request.Request(url, headers=headers), timeout=60
            )
        except urllib.error.HTTPError as err:
            if not (have and err.code == 416):  # 416: nothing left to send, the part is whole
                raise
            response = None
        if response is not None:
            with response:
                if response.status != 206:  # the whole archive (again)
                    have = 0
                rest = int(response.headers.get("Content-Length") or 0)
                part.parent.mkdir(parents=True, exist_ok=True)
                total = have + rest if rest else None
                bar = tqdm(
                    total=total, initial=have, unit="B", unit_scale=True, disable=not progress
                )
                received = 0
                with open(part, "ab" if have else "wb") as out, bar:
                    while chunk := response.read(1 << 20):
                        out.write(chunk)
                        received += len(chunk)
                        bar.update(len(chunk))
                if rest and received < rest:  # read(n) ends quietly when the server hangs up
                    raise OSError(f"the connection closed after {received} of {rest} bytes")
        shutil.copyfile(part, output_file)

    return fetch


def _drop_partial(part: Path) -> None:
    part.unlink(missing_ok=True)
    try:
        part.parent.rmdir()  # only when empty
    except OSError:
        pass


MIRROR_SCHEMES = ("http", "https", "ftp")


def check_mirror(mirror: str, source: str) -> None:
    """Refuse a mirror that is not a base URL (`source`: the option or variable that gave it),
    before a download tries it and fails with an error that names neither."""
    from urllib.parse import urlsplit

    parts = urlsplit(mirror)
    if parts.scheme not in MIRROR_SCHEMES or not parts.netloc:
        raise DatasetError(
            f"{source} {mirror!r} is not a base URL: expected {', '.join(MIRROR_SCHEMES)}://HOST"
            f"/PATH laid out as {TUM_BASE_URL} (freiburg1/rgbd_dataset_freiburg1_desk.tgz, ...)"
        )


def download(
    target: str,
    root: Path,
    sha256: str | None = None,
    mirror: str | None = None,
    progress: bool = True,
) -> tuple[Path, str]:
    """Fetch and unpack a known sequence or an archive URL into `root`; (folder, its sha256).

    A known name unpacks into root/NAME (root/fr1/desk), a URL into root/ARCHIVE_STEM. `mirror`
    replaces TUM's base URL for known names. A folder already there is returned as it is
    (its sha256 is then "").
    """
    import pooch

    if "://" in target:
        if mirror:
            raise DatasetError(f"{target}: --mirror applies to known names, not to a URL")
        url, known, name = target, None, _archive_stem(target)
    elif target in SEQUENCES:
        known = SEQUENCES[target]
        url = (mirror or TUM_BASE_URL).rstrip("/") + "/" + known.archive
        name = target
    else:
        raise DatasetError(f"{target}: neither a known sequence ({', '.join(SEQUENCES)}) nor a URL")
    checksum = sha256 or (known.sha256 if known else None)
    if checksum is not None and not re.fullmatch(r"[0-9a-fA-F]{64}", checksum):
        raise DatasetError(f"--sha256 expects 64 hexadecimal digits, got {checksum!r}")
    folder = Path(root) / name
    if folder.is_dir():
        return folder, ""
    folder.parent.mkdir(parents=True, exist_ok=True)
    pooch.get_logger().setLevel("WARNING")  # the sha256 is reported by the caller
    work = Path(tempfile.mkdtemp(prefix=f".{folder.name}.", dir=folder.parent))
    file_name = url.rsplit("/", 1)[-1].split("?")[0]
    part = Path(root) / PARTIAL / file_name
    try:
        try:
            archive = Path(
                pooch.retrieve(
                    url,
                    known_hash=f"sha256:{checksum}" if checksum else None,
                    fname=file_name,
                    path=work,
                    downloader=resumable_fetch(part, progress),
                )
            )
        except ValueError as err:  # pooch: the checksum does not match, or a bad URL
            _drop_partial(part)
            got = re.search(r"but got ([0-9a-f]+)", str(err))
            if checksum is None or got is None:
                message = " ".join(str(err).split())
                raise DatasetError(f"{url}: cannot download ({message})") from None
            raise DatasetError(
                f"{url}: corrupt or truncated download: sha256 {got.group(1) if got else '?'}"
                f", expected {checksum}; nothing was kept"
            ) from None
        except Exception as err:  # noqa: BLE001 - urllib's errors and OSError alike
            message = " ".join(str(err).split())
            kept = part.stat().st_size if part.is_file() else 0
            resume = f"; {kept} bytes kept, the same command resumes" if kept else ""
            raise DatasetError(f"{url}: download failed ({message}){resume}") from None
        _drop_partial(part)  # a whole response: whatever it unpacks to, it is not resumed
        digest = pooch.file_hash(str(archive), alg="sha256")
        sequence = _unpack(archive, work / "unpacked", url)
        if known is not None and not (sequence / "intrinsics.json").is_file():
            values = known.camera.to_json()
            (sequence / "intrinsics.json").write_text(strict_dumps(values, indent=2) + "\n")
        sequence.rename(folder)  # complete: only now does the cache hold it
    finally:
        shutil.rmtree(work, ignore_errors=True)
        if not folder.is_dir() and folder.parent != Path(root):
            try:  # fr1/ made for a download that failed: leave no empty folder either
                folder.parent.rmdir()
            except OSError:
                pass
    return folder, digest


def _unpack(archive: Path, into: Path, url: str) -> Path:
    """Unpack a tar archive and return the folder in it that holds the TUM lists."""
    try:
        with tarfile.open(archive) as tar:
            tar.extractall(into, filter="data")
    except (tarfile.TarError, EOFError, zlib.error, OSError) as err:
        message = " ".join(str(err).split())
        raise DatasetError(
            f"{url}: archive is truncated or corrupt ({message}); nothing was kept"
        ) from None
    for lists in sorted(into.rglob("rgb.txt")) + sorted(into.rglob("associations.txt")):
        return lists.parent
    raise DatasetError(f"{url}: the archive holds no TUM sequence (no rgb.txt); nothing was kept")
